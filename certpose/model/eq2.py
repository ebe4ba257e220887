r"""Eq. (2) of the paper as a weighted TLS problem: its construction, solution and certificate.

**Eq. (2) and its weights.** For object points ``p_i`` and grid points ``y_j`` (the centres of
occupied voxels: neither empty nor unobserved, NOTES.md 1.4),

.. math:: c_{ij} = \log p_O(y_j) + \beta f_{scn}(y_j)^T z_i .

``c_ij`` is a log-probability (usually negative), but a TLS cost ``sum w_ij min(r_ij^2, eps^2)``
only pulls ``p_i`` towards ``y_j`` when ``w_ij >= 0``. We use the mapping of NOTES.md 1.2:

.. math:: w_{ij} = c_{ij} - c_{floor}, \qquad c_{floor} = c_{min} - \beta ,

``c_floor`` being the lowest value ``c_ij`` can take (a classifier negative, ``log p_O = c_min``,
with the least similar unit descriptors, ``f^T z = -1``), so every weight is ``>= 0`` without
clipping. Minimising eq. (2) then maximises ``sum_ij w_ij (eps^2 - r_ij^2)_+``, an Epanechnikov
kernel smoothing of eq. (1) restricted to occupied voxels (up to the constant ``N c_floor``).

**Sparsification (NOTES.md 1.3).** Each of ``num_object_points`` object points (farthest-point
sample) keeps its ``top_k`` grid points of highest weight: ``K = N k`` weighted
correspondences, at least ``(k-1)/k`` of them outliers. The problem is solved by
:func:`solvers.solve_registration` (max-clique pruning + GNC-TLS) and certified by
:func:`solvers.certify.certify_result`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from certpose.geometry.objects import ObjectModel
    from certpose.model.classifier import ObjectClassification
    from certpose.model.likelihood import LikelihoodParams
    from solvers import RegistrationResult, WeightedTLSProblem

__all__ = ["Eq2Params", "Eq2Problem", "WIDE_EQ2", "build_eq2_problem", "solve_eq2", "certify_eq2"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Eq2Params:
    """Construction of the eq. (2) weighted TLS problem.

    Attributes
    ----------
    num_object_points : int
        Object points used (farthest-point sample); the problem has ``num_object_points * top_k``
        correspondences.
    top_k : int
        Grid points kept per object point (highest weight).
    noise_bound : float or None
        TLS inlier bound ``eps`` in metres; default one scene voxel (the grid's resolution).
        Larger bounds make the consistency graph of the pruning step denser and its exact
        max-clique search much slower.

    Notes
    -----
    Measured on the 60 YCB-Video pairs of the shared scenes (geometry-only FPFH models, mask
    classifier; ``examples/bench_eq2.py``). FPFH barely ranks the right voxel above the others:
    at the true pose its median rank among a point's candidates is about a third of the
    classifier's positives (150-250 of 300-1500). With the defaults (40 x top-4, N = 160) the
    right voxel is a candidate for a median of 1 object point (none in 19 pairs) and the raw
    minimiser is within 1 cm ADD-S in 14 of 60 pairs; with ``WIDE_EQ2`` (100 x top-40,
    N = 4000), for a median of 9 object points (3-25; more than any of 200 random rotations about
    the object's centre gathers), within 1 cm in 31 of 60 (20 of them 180-deg flips). Neither
    carries the MLE: the refined eq. (2) pose wins, or lands within 0.5 cm and 2 deg of the
    winner, in 6 of 60 pairs with the defaults and 3 of 60 with ``WIDE_EQ2``. The defaults stay
    because the wider problem costs its certificate (the clique bound does not close at
    N = 4000: none of the 60 is certified, against all 60 at N = 160, where the certificate
    covers the eq. (2) minimiser, not the returned pose), about 5-14% of the MLE time and a
    second compiled clique search on a first run. A noise bound of 1.5 voxels gave 32 of 60;
    N = 10,000 did no better than 4000 on the 18 first frames, and the certifier's O(N^2)
    graph then costs 4-8 s.
    """

    num_object_points: int = 40
    top_k: int = 4
    noise_bound: float | None = None

    def __post_init__(self) -> None:
        if int(self.num_object_points) < 3:
            raise ValueError(f"`num_object_points` must be >= 3, got {self.num_object_points}.")
        if int(self.top_k) < 1:
            raise ValueError(f"`top_k` must be >= 1, got {self.top_k}.")
        if self.noise_bound is not None and not (
            math.isfinite(self.noise_bound) and self.noise_bound > 0
        ):
            raise ValueError(f"`noise_bound` must be positive, got {self.noise_bound}.")


WIDE_EQ2 = Eq2Params(num_object_points=100, top_k=40)
"""Eq. (2) with the right voxel among the candidates of many more object points (see
:class:`Eq2Params`'s notes): a better raw minimiser, no certificate."""


@dataclass(frozen=True, eq=False)
class Eq2Problem:
    """Eq. (2) as a weighted TLS problem.

    Attributes
    ----------
    problem : WeightedTLSProblem
        ``source`` = object points (each repeated ``top_k`` times), ``target`` = grid points
        ``y_j``, ``weights`` = ``c_ij - c_floor``; its ``T_target_source`` is ``T_scene_object``.
    object_index : (K,) ndarray of int64
        Row of the object model of each correspondence.
    grid_points : (M, 3) ndarray
        All candidate grid points ``y_j`` (occupied voxel centres), scene frame, metres.
    grid_index : (K,) ndarray of int64
        Row of ``grid_points`` of each correspondence.
    c : (K,) ndarray
        The log-probabilities ``c_ij`` of the kept pairs.
    c_floor : float
        The offset of the weight mapping (``c_min - beta``).
    """

    problem: WeightedTLSProblem
    object_index: NDArray[np.int64]
    grid_points: NDArray[np.float64]
    grid_index: NDArray[np.int64]
    c: NDArray[np.float64]
    c_floor: float


def build_eq2_problem(
    scene: Any,
    classification: ObjectClassification,
    object_model: ObjectModel,
    *,
    params: Eq2Params | None = None,
    likelihood_params: LikelihoodParams | None = None,
    rng: np.random.Generator | int | None = None,
) -> Eq2Problem:
    """Build the sparsified eq. (2) problem (see the module docstring for the weights).

    Parameters
    ----------
    scene : SceneField
    classification : ObjectClassification
        On the scene's grid.
    object_model : ObjectModel
    params : Eq2Params, optional
    likelihood_params : LikelihoodParams, optional
        Supplies ``beta``.
    rng : numpy Generator, int or None
        Seeds the farthest-point sample.

    Returns
    -------
    Eq2Problem

    Raises
    ------
    ValueError
        Mismatched descriptor dimensions, NaN descriptors, fewer than 3 occupied voxels.
    """
    from certpose.model.grid import OCCUPIED, scene_grid_spec
    from certpose.model.likelihood import LikelihoodParams
    from solvers import WeightedTLSProblem

    params = params or Eq2Params()
    beta = (likelihood_params or LikelihoodParams()).beta
    grid = scene_grid_spec(scene)
    state = np.asarray(scene.state)
    occ = np.argwhere(state == OCCUPIED)
    if occ.shape[0] < 3:
        raise ValueError(f"The scene has {occ.shape[0]} occupied voxel(s); eq. (2) needs at least 3.")
    desc = np.asarray(scene.descriptors)
    if desc.shape[-1] != object_model.dim:
        raise ValueError(
            f"Descriptor dimensions differ: object {object_model.dim}, scene {desc.shape[-1]}."
        )
    s = desc[occ[:, 0], occ[:, 1], occ[:, 2]].astype(np.float32)
    if not np.all(np.isfinite(s)):
        raise ValueError("`scene.descriptors` contains NaN or inf values at occupied voxels.")
    log_p = np.asarray(classification.log_p, dtype=np.float64)[occ[:, 0], occ[:, 1], occ[:, 2]]
    y = grid.centres(occ)
    sub = object_model.subsample(int(params.num_object_points), rng=rng)
    # Map the subsample back to rows of the full model (subsample keeps row order).
    obj_rows = _rows_of(object_model.points, sub.points)
    k = min(int(params.top_k), y.shape[0])
    c_all = log_p[None, :] + beta * (sub.descriptors.astype(np.float32) @ s.T)
    top = np.argpartition(-c_all, k - 1, axis=1)[:, :k]
    c = np.take_along_axis(c_all, top, axis=1)
    c_floor = float(classification.c_min) - beta
    w = c - c_floor
    if w.min() < -1e-6:  # only possible with descriptor norms > 1 or log_p < c_min
        raise ValueError(f"A weight c_ij - c_floor is negative ({w.min():.3g}); check the inputs.")
    eps = params.noise_bound if params.noise_bound is not None else grid.voxel_size
    n = sub.points.shape[0]
    src = np.repeat(sub.points, k, axis=0)
    problem = WeightedTLSProblem(
        src, y[top.reshape(-1)], noise_bound=eps, weights=np.maximum(w.reshape(-1), 0.0)
    )
    log.info("eq. (2): %d object points x top-%d of %d grid points = %d correspondences",
             n, k, y.shape[0], problem.n)
    return Eq2Problem(
        problem,
        np.repeat(obj_rows, k),
        y,
        top.reshape(-1).astype(np.int64),
        c.reshape(-1).astype(np.float64),
        c_floor,
    )


def _rows_of(points: NDArray[np.float64], subset: NDArray[np.float64]) -> NDArray[np.int64]:
    from scipy.spatial import cKDTree

    return cKDTree(points).query(subset)[1].astype(np.int64)


def solve_eq2(
    eq2: Eq2Problem, *, certify: bool = True, time_limit: float | None = None
) -> RegistrationResult:
    """Solve eq. (2) with max-clique pruning + GNC-TLS; attach a certificate when possible.

    The certificate comes from :func:`certify_eq2`; ``time_limit`` (seconds) is passed to the
    certifier.
    """
    from dataclasses import replace

    from solvers import solve_registration

    t0 = time.perf_counter()
    result = solve_registration(eq2.problem, method="auto")
    result = replace(result, info={**result.info, "registration_time": time.perf_counter() - t0})
    if not certify:
        return replace(result, info={**result.info, "certificate_message": "not requested"})
    return certify_eq2(eq2, result, time_limit=time_limit)


def certify_eq2(
    eq2: Eq2Problem, result: RegistrationResult, *, time_limit: float | None = None
) -> RegistrationResult:
    """Certify an eq. (2) solution with :func:`solvers.certify.certify_result`.

    If the certifier fails, ``result`` comes back with ``certificate=None`` and
    ``info["certificate_message"]`` says why. The certifier may return
    a better pose than ``result``'s (it then says so in its message).
    """
    from dataclasses import replace

    from solvers.certify import certify_result

    try:
        t0 = time.perf_counter()
        certified = certify_result(eq2.problem, result, time_limit=time_limit)
        result = replace(result, info={**result.info, "certify_time": time.perf_counter() - t0})
    except Exception as exc:  # a failing backend must not lose the pose
        msg = f"certification failed: {type(exc).__name__}: {exc}"
        log.warning("eq. (2): %s", msg)
        return replace(result, info={**result.info, "certificate_message": msg})
    return replace(certified, info={**result.info, **certified.info,
                                    "certificate_message": "certifier ran"})
