r"""Eq. (2) of the paper as a weighted TLS problem: its construction, solution and certificate.

**Eq. (2) and its weights.** For object points ``p_i`` and grid points ``y_j`` (the centres of
occupied voxels: neither empty nor unobserved; empty space is ``-inf`` and unobserved 0 in
eq. (1), so only occupied voxels can attract a point),

.. math:: c_{ij} = \log p_O(y_j) + \beta f_{scn}(y_j)^T z_i .

``c_ij`` is a log-probability (usually negative), but a TLS cost ``sum w_ij min(r_ij^2, eps^2)``
only pulls ``p_i`` towards ``y_j`` when ``w_ij >= 0``. We use the mapping

.. math:: w_{ij} = c_{ij} - c_{floor}, \qquad c_{floor} = c_{min} - \beta ,

``c_floor`` being the lowest value ``c_ij`` can take (a classifier negative, ``log p_O = c_min``,
with the least similar unit descriptors, ``f^T z = -1``), so every weight is ``>= 0`` without
clipping. Minimising eq. (2) then maximises ``sum_ij w_ij (eps^2 - r_ij^2)_+``, an Epanechnikov
kernel smoothing of eq. (1) restricted to occupied voxels (up to the constant ``N c_floor``).

**Sparsification.** The ``N x M`` pairs of object and grid points are far too many. Which pairs ``(i, j)`` the problem keeps is ours to choose
(the weights are ``c_ij - c_floor`` either way):

* *by descriptor* (no seeds): each of ``num_object_points`` object points (farthest-point
  sample) keeps its ``top_k`` grid points of highest weight: ``K = N k`` weighted
  correspondences, at least ``(k-1)/k`` of them outliers;
* *by proximity to seed poses* (:func:`estimate_eq2`, what :func:`~certpose.estimation.mle.estimate_mle`
  does, with the coarse eq. (1) search's leading distinct hypotheses as seeds): each of
  ``seed_object_points`` object points keeps, under every seed pose, its ``seed_neighbors``
  nearest occupied voxels within ``seed_radius`` (the union over the seeds); the minimiser then
  picks among the seeds' basins by eq. (2)'s own support, and ``local_rounds`` rounds rebuild
  the candidates around it (the voxels within two noise bounds).
  :func:`solve_eq2_about_seeds` keeps every seed's minimiser: the MLE refines each on eq. (1),
  which chooses among their basins better than eq. (2)'s support (see :class:`Eq2Params`).
  The MLE seeds every hypothesis it refines (16): the first ``num_seeds`` problems are solved
  with the max-clique pruning and GNC, the ``gnc_seeds`` after them with GNC alone (about a
  seed most pairs agree; measured, the same outcomes at half the time). The local rounds of
  the minimiser it certifies begin where that minimiser ended on eq. (1)
  (:meth:`SeededEq2.local_rounds`'s ``start``).

What a seeded problem does, measured (18 cross-scene pairs, mask classifier; the 37 seeds within
30 degrees of the MLE's winner): its minimiser lies within a degree or two of its seed (rotation
from the winner changed by a median -0.5 degrees, 10-90% -2.1..+1.2; translation by under a
millimetre). Eq. (2) registers each seed locally and certifiably; the choice of basin is left to
eq. (1), whose free-space term and appearance tell a can's or a banana's 180-degree turns apart
where eq. (2)'s support does not.

What eq. (2) decides and what it does not: about each seed it finds the pose that the voxels
near that seed support best (an Epanechnikov-smoothed eq. (1) without free space), which is
seldom more than a degree or two from the seed, and it certifies the one it is asked to. It
does not choose among the seeds' basins (eq. (1) does, after refining every minimiser), nor
find a basin no seed is in (a near-symmetric turn that the MLE's mode step tries later). The
pose it certifies is eq. (2)'s minimiser in the basin of the best refined minimiser when the
refinement ends, or, when the MLE's winner descends from another hypothesis (a turn, or one
that hopped past it), eq. (2)'s minimiser about the winner, solved again.

Why seeds: on the 18 cross-scene YCB-Video pairs of ``examples/benchmarks/bench_box.py`` (appearance
models, mask classifier) the descriptors barely rank the right voxel among the classifier's
positives, colour or shape alike: at the true pose its median rank is 0.16-0.49 of the
positives (0.5 is chance; a banana or a bottle is one colour, and local shape on a cylinder is
the same everywhere), so no ``k`` puts it among the candidates of enough object points.

The problem is solved by :func:`solvers.solve_registration` (max-clique pruning + GNC-TLS) and
certified by :func:`solvers.certify.certify_result`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from certpose.geometry.objects import ObjectModel
    from certpose.model.classifier import ObjectClassification
    from certpose.model.likelihood import LikelihoodParams
    from solvers import RegistrationResult, WeightedTLSProblem

__all__ = ["Eq2Params", "Eq2Problem", "SeededEq2", "WIDE_EQ2", "build_eq2_problem", "estimate_eq2",
           "solve_eq2_about_seeds", "solve_eq2", "certify_eq2"]

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
    num_seeds : int
        Seed poses whose problems are solved with the max-clique pruning and GNC (the first
        ones given; 0: the MLE builds the candidates by descriptor even when it has seeds).
    seed_object_points : int
        Object points (farthest-point sample) of the seeded problem.
    seed_neighbors : int
        Occupied voxels kept per object point and seed: the nearest ones within ``seed_radius``.
    seed_radius : float
        Metres.
    gnc_seeds : int
        Further seeds (those after the first ``num_seeds``) whose problems
        :func:`solve_eq2_about_seeds` solves with GNC alone, without the max-clique pruning:
        about a seed most pairs are mutually consistent, and the minimiser stays in the seed's
        basin either way (see the notes).
    local_rounds : int
        Rounds of :func:`estimate_eq2` on the candidates within two noise bounds of the last
        minimiser (its 8 nearest voxels per object point).
    seed_mode : {"each", "union"}
        ``"each"``: one problem per seed, solved; the minimisers compete on eq. (2)'s support
        (``sum_ij w_ij (1 - r_ij^2 / eps^2)_+`` over every voxel near them), the best one
        goes on to the local rounds. ``"union"``: one problem over all the seeds' candidates.

    Notes
    -----
    The seeded problem (what :func:`~certpose.estimation.mle.estimate_mle` builds), measured
    with ``examples/benchmarks/bench_box.py --models appearance`` (18 cross-scene pairs, appearance
    models, load average 12-19; main's descriptor top-4 of 40 points before -> seeds, 8 seeds,
    100 object points, 3 voxels within 2 cm per seed, 2 local rounds):

    ========================  ==========================  ===========================
    classifier, seed          raw eq. (2) ADD-S <= 1 cm    refined eq. (2) the winner
                                                            or within 0.5 cm / 2 deg
    ========================  ==========================  ===========================
    mask, 0                   3/18 -> 15/18                3/18 -> 4/18
    mask, 1                   5/18 -> 18/18                4/18 -> 6/18
    ========================  ==========================  ===========================

    Every seed's minimiser refined on eq. (1) as the coarse hypotheses are (each replacing its
    seed; ``examples/benchmarks/bench_box.py --models appearance --seed 0``, load 7-9): the refined eq. (2)
    hypothesis is the winner or within 0.5 cm / 2 deg of it in 7/18 -> 17/18 pairs (mask) and
    5/18 -> 15/18 (box only, best buddies), and the final poses are unchanged (ADD-S 18/18, right
    15/18, eq. (1) >= refined truth - 1 nat 18/18, in both modes). The highest support's
    minimiser, refined, was turned by 150-180 degrees from the winner in 8 of the 18 pairs in
    either mode; the raw (certified) eq. (2) pose is now the one whose minimiser climbed highest
    on eq. (1): turned from the winner in 8 -> 1 (mask) and 8 -> 3 (box only) pairs, within
    10 degrees of the truth in 7 -> 11 and 5 -> 8, ADD-S <= 1 cm unchanged (18/18, 16/18). The
    raw pose is hardly better than its seed: most are 5-25 degrees off, and eq. (1)'s
    refinement takes them the rest of the way.

    Inliers at the true pose of the seeded problem: 1-45 of 1000-1900 pairs (1-27 object
    points of 100); of main's 160: 0-3. The eq. (2) stage takes 0.34 s median (0.18 s
    before, interleaved, load about 14). None of the seeded problems is certified within
    the 1 s limit (``iteration_limit``; main's certified 2 of 18 with appearance models).
    Eq. (2) has no free-space term: it often prefers a can's or a banana's 180-degree turn
    that eq. (1) with appearance rejects, so its refined pose ends in another basin than the
    winner's in most pairs. ``seed_mode="union"`` gave 17/18 and 7/18 (mask, seed 0);
    local rounds with the clique search 18/18 on both seeds but 2.5 s a frame.

    The descriptor problem (no seeds), measured on the 60 YCB-Video pairs of the shared scenes (geometry-only FPFH models, mask
    classifier; ``examples/benchmarks/bench_eq2.py``). FPFH barely ranks the right voxel above the others:
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

    Every hypothesis the MLE refines seeded (16: ``num_seeds=1`` with the pruning, 15 more by
    GNC alone, ``gnc_seeds``), and the certified minimiser's local rounds begun at its refined
    pose (:meth:`SeededEq2.local_rounds`), against 8 seeds with the pruning and the rounds begun
    at the raw minimiser (load 7-9 on 2 cores, interleaved with other work):

    * ``examples/benchmarks/bench_eq2.py`` (60 geometry-only pairs): refined eq. (2) the winner or within
      0.5 cm / 2 deg 39/60 -> 49/60, raw ADD-S <= 1 cm 58/60 -> 59/60, MLE ADD-S 60/60 both;
      the eq. (2) stage's median 116 -> 53 ms. Eight seeds with the pruning and 8 by GNC gave
      the same outcomes pair for pair in 166 ms. The 11 pairs still lost are won by a
      near-symmetric turn of the search's winner (the MLE's mode step, after eq. (2)).
    * ``examples/benchmarks/bench_box.py --models appearance --seed 0`` (18 cross-scene pairs): box only,
      raw ADD-S <= 1 cm 14/18 -> 16/18 and refined eq. (2) the winner or near 15/18 -> 16/18;
      mask 18/18 and 18/18 (both before too); the final poses unchanged (ADD-S 18/18, right
      15/18, eq. (1) >= refined truth - 1 nat 18/18 in both modes). The two raw misses left
      were the mustard bottle in 0002/000010 and 000020, box only (1.12 and 1.29 cm): every
      refined minimiser there is the bottle turned by 180 degrees, and the winner is that
      pose's turn; with eq. (2) solved again about such a winner, 0.25 and 0.27 cm (18/18).
    """

    num_object_points: int = 40
    top_k: int = 4
    noise_bound: float | None = None
    num_seeds: int = 1
    gnc_seeds: int = 15
    seed_object_points: int = 100
    seed_neighbors: int = 3
    seed_radius: float = 0.02
    local_rounds: int = 2
    seed_mode: str = "each"

    def __post_init__(self) -> None:
        if int(self.num_object_points) < 3:
            raise ValueError(f"`num_object_points` must be >= 3, got {self.num_object_points}.")
        if int(self.top_k) < 1:
            raise ValueError(f"`top_k` must be >= 1, got {self.top_k}.")
        if int(self.num_seeds) < 0:
            raise ValueError(f"`num_seeds` must be >= 0, got {self.num_seeds}.")
        if int(self.gnc_seeds) < 0:
            raise ValueError(f"`gnc_seeds` must be >= 0, got {self.gnc_seeds}.")
        if int(self.seed_object_points) < 3:
            raise ValueError(f"`seed_object_points` must be >= 3, got {self.seed_object_points}.")
        if int(self.seed_neighbors) < 1:
            raise ValueError(f"`seed_neighbors` must be >= 1, got {self.seed_neighbors}.")
        if not (math.isfinite(self.seed_radius) and self.seed_radius > 0):
            raise ValueError(f"`seed_radius` must be positive, got {self.seed_radius}.")
        if int(self.local_rounds) < 0:
            raise ValueError(f"`local_rounds` must be >= 0, got {self.local_rounds}.")
        if self.seed_mode not in ("each", "union"):
            raise ValueError(f"`seed_mode` must be 'each' or 'union', got {self.seed_mode!r}.")
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
    seeds: ArrayLike | None = None,
    seed_radius: float | None = None,
    seed_neighbors: int | None = None,
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
    seeds : (S, 4, 4) array_like, optional
        Poses ``T_scene_object``: keep the pairs near them (``seed_object_points`` object
        points, each with its ``seed_neighbors`` nearest occupied voxels within ``seed_radius``
        under every seed) instead of the descriptors' ``top_k``.
    seed_radius, seed_neighbors : optional
        Override ``params``'s (metres; count).

    Returns
    -------
    Eq2Problem

    Raises
    ------
    ValueError
        Mismatched descriptor dimensions, NaN descriptors, fewer than 3 occupied voxels, seeds
        of the wrong shape, or seeds near fewer than 3 pairs.
    """
    params = params or Eq2Params()
    inputs = _prepare(scene, classification, object_model, params, likelihood_params)
    n = int(params.num_object_points if seeds is None else params.seed_object_points)
    sub = object_model.subsample(n, rng=rng)
    return _problem(inputs, sub, _rows_of(object_model.points, sub.points), params, seeds,
                    seed_radius, seed_neighbors)


@dataclass(frozen=True, eq=False)
class _Inputs:
    """What every eq. (2) problem of one scene, classification and object shares."""

    y: NDArray[np.float64]  # occupied voxel centres
    s: NDArray[np.float32]  # their descriptors
    log_p: NDArray[np.float64]
    beta: float
    c_floor: float
    eps: float
    tree: Any  # cKDTree of y


def _prepare(scene: Any, classification: ObjectClassification, object_model: ObjectModel,
             params: Eq2Params, likelihood_params: LikelihoodParams | None) -> _Inputs:
    from scipy.spatial import cKDTree

    from certpose.model.grid import OCCUPIED, scene_grid_spec
    from certpose.model.likelihood import LikelihoodParams

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
    eps = params.noise_bound if params.noise_bound is not None else grid.voxel_size
    return _Inputs(y, s, log_p, float(beta), float(classification.c_min) - beta, float(eps),
                   cKDTree(y))


def _problem(inputs: _Inputs, sub: ObjectModel, obj_rows: NDArray[np.int64], params: Eq2Params,
             seeds: ArrayLike | None, seed_radius: float | None,
             seed_neighbors: int | None, *, checked: bool = False) -> Eq2Problem:
    """``checked``: ``seeds`` is already an ``(S, 4, 4)`` array of validated transforms (the
    seeded solves build dozens of problems from their own minimisers: no need to check each)."""
    from solvers import WeightedTLSProblem

    y, s, log_p, beta = inputs.y, inputs.s, inputs.log_p, inputs.beta
    if seeds is None:
        k = min(int(params.top_k), y.shape[0])
        c_all = log_p[None, :] + beta * (sub.descriptors.astype(np.float32) @ s.T)
        top = np.argpartition(-c_all, k - 1, axis=1)[:, :k]
        rows = np.repeat(np.arange(sub.points.shape[0]), k)
        cols = top.reshape(-1)
        c = np.take_along_axis(c_all, top, axis=1).reshape(-1).astype(np.float64)
        how = f"top-{k} by descriptor"
    else:
        T = np.asarray(seeds) if checked else _check_transforms(seeds, "seeds")
        radius = float(params.seed_radius if seed_radius is None else seed_radius)
        k = min(int(params.seed_neighbors if seed_neighbors is None else seed_neighbors), y.shape[0])
        q = np.einsum("sij,nj->sni", T[:, :3, :3], sub.points) + T[:, None, :3, 3]
        dist, nn = inputs.tree.query(q.reshape(-1, 3), k=k, distance_upper_bound=radius)
        dist, nn = dist.reshape(-1, k), nn.reshape(-1, k)
        keep = np.isfinite(dist)
        rows = np.broadcast_to(np.tile(np.arange(sub.points.shape[0]), T.shape[0])[:, None],
                               keep.shape)[keep]
        # The seeds' candidate sets overlap (nearby seeds, a pair near two seeds): each pair once
        # (one seed's are distinct already: a point's neighbours are).
        pairs = np.stack([rows, nn[keep]], axis=1)
        if T.shape[0] > 1:
            pairs = np.unique(pairs, axis=0)
        if pairs.shape[0] < 3:
            raise ValueError(f"The {T.shape[0]} seed pose(s) put only {pairs.shape[0]} object "
                             f"point(s) within {radius:g} m of an occupied voxel; eq. (2) needs 3.")
        rows, cols = pairs[:, 0], pairs[:, 1]
        c = log_p[cols] + beta * np.einsum(
            "ij,ij->i", sub.descriptors[rows].astype(np.float64), s[cols].astype(np.float64))
        how = f"near {T.shape[0]} seed pose(s) (<= {k} voxels within {radius:g} m)"
    w = c - inputs.c_floor
    if w.min() < -1e-6:  # only possible with descriptor norms > 1 or log_p < c_min
        raise ValueError(f"A weight c_ij - c_floor is negative ({w.min():.3g}); check the inputs.")
    problem = WeightedTLSProblem(
        sub.points[rows], y[cols], noise_bound=inputs.eps, weights=np.maximum(w, 0.0)
    )
    log.debug("eq. (2): %d object points, %s of %d grid points: %d correspondences",
              sub.points.shape[0], how, y.shape[0], problem.n)
    # object_index: rows of the full model (the subsample keeps row order).
    return Eq2Problem(problem, obj_rows[rows], y, cols.astype(np.int64),
                      c.astype(np.float64), inputs.c_floor)


@dataclass(frozen=True, eq=False)
class SeededEq2:
    """Eq. (2) solved about each seed pose (:func:`solve_eq2_about_seeds`).

    Attributes
    ----------
    seed_rows : (S',) ndarray of int64
        Rows of ``seeds`` near enough occupied voxels to pose a problem, in seed order.
    problems : tuple of Eq2Problem
        Their problems (S').
    results : tuple of RegistrationResult
        Their minimisers (``T_target_source`` = ``T_scene_object``), not certified.
    supports : (S',) ndarray
        Eq. (2)'s support of each minimiser (see :func:`_support`); the highest is eq. (2)'s own
        choice among the seeds' basins.
    """

    seed_rows: NDArray[np.int64]
    problems: tuple[Eq2Problem, ...]
    results: tuple[RegistrationResult, ...]
    supports: NDArray[np.float64]
    _rounds: Any = field(repr=False)

    @property
    def minimisers(self) -> NDArray[np.float64]:
        """``(S', 4, 4)``: each problem's minimiser."""
        return np.stack([r.T_target_source for r in self.results])

    @property
    def best_supported(self) -> int:
        """Index (into ``seed_rows``) of the highest support, the first of equals."""
        return int(np.argmax(self.supports))

    def local_rounds(self, i: int, start: ArrayLike | None = None
                     ) -> tuple[Eq2Problem, RegistrationResult]:
        """Member ``i``'s problem and minimiser after ``Eq2Params.local_rounds`` rounds on the
        voxels within two noise bounds of its minimiser (the last round's problem).

        ``start`` ((4, 4), ``T_scene_object``): begin the rounds there instead of at the
        minimiser, e.g. at the minimiser once refined on eq. (1) (what the MLE certifies). The
        rounds register locally (each moves the pose by well under a noise bound or two), so the
        result is eq. (2)'s minimiser in ``start``'s basin. Ignored without local rounds.
        """
        if start is None:
            return self._rounds(self.problems[i], self.results[i])
        T = _check_transforms(start, "start")
        if T.shape[0] != 1:
            raise ValueError(f"Expected `start` to be one (4, 4) pose, got {np.shape(start)}.")
        moved = self.results[i]._with_transform(T[0].copy())
        eq2, result = self._rounds(self.problems[i], moved)
        if result is moved:  # no round ran: ``start`` minimises nothing, keep the minimiser
            return self.problems[i], self.results[i]
        return eq2, result


def estimate_eq2(
    scene: Any,
    classification: ObjectClassification,
    object_model: ObjectModel,
    seeds: ArrayLike,
    *,
    params: Eq2Params | None = None,
    likelihood_params: LikelihoodParams | None = None,
    rng: np.random.Generator | int | None = None,
) -> tuple[Eq2Problem, RegistrationResult]:
    """Eq. (2) on the candidates near seed poses, solved; then ``local_rounds`` rounds near its
    minimiser (see the module docstring). Not certified (see :func:`certify_eq2`).

    Parameters
    ----------
    scene, classification, object_model, params, likelihood_params
        As :func:`build_eq2_problem`.
    seeds : (S, 4, 4) array_like
        Poses ``T_scene_object``, best first (the first ``params.num_seeds`` and
        ``params.gnc_seeds`` more are used).
    rng : numpy Generator, int or None
        Seeds the farthest-point sample (the same object points in every round).

    Returns
    -------
    eq2 : Eq2Problem
        The last round's problem (the one ``result`` minimises).
    result : RegistrationResult
    """
    out = solve_eq2_about_seeds(scene, classification, object_model, seeds, params=params,
                                likelihood_params=likelihood_params, rng=rng)
    return out.local_rounds(out.best_supported)


def solve_eq2_about_seeds(
    scene: Any,
    classification: ObjectClassification,
    object_model: ObjectModel,
    seeds: ArrayLike,
    *,
    params: Eq2Params | None = None,
    likelihood_params: LikelihoodParams | None = None,
    rng: np.random.Generator | int | None = None,
) -> SeededEq2:
    """Eq. (2) about seed poses, every minimiser kept (the MLE refines each one on eq. (1));
    :func:`estimate_eq2` is this, then the local rounds of the highest support's.

    With ``seed_mode="each"`` one problem per seed is solved; with ``"union"`` one problem over
    all the seeds' candidates, whose minimiser is the only one. No local rounds yet (see
    :meth:`SeededEq2.local_rounds`). The parameters are those of :func:`estimate_eq2`.

    Returns
    -------
    SeededEq2

    Raises
    ------
    ValueError
        Seeds of the wrong shape, or none of them near an occupied voxel.
    """
    from solvers import solve_registration

    params = params or Eq2Params()
    n_full = max(int(params.num_seeds), 1)
    T = _check_transforms(seeds, "seeds")[: n_full + int(params.gnc_seeds)]
    inputs = _prepare(scene, classification, object_model, params, likelihood_params)
    sub = object_model.subsample(int(params.seed_object_points), rng=rng)
    rows = _rows_of(object_model.points, sub.points)

    def near(T_: NDArray[np.float64], radius: float | None = None,
             k: int | None = None) -> Eq2Problem:
        return _problem(inputs, sub, rows, params, T_, radius, k, checked=True)

    def local(T_: NDArray[np.float64]) -> Eq2Problem:
        # Every voxel within two noise bounds of each object point (its 8 nearest): the support
        # of a pose is then eq. (2)'s unsparsified objective.
        return near(T_[None], 2.0 * inputs.eps, 8)

    def rounds(eq2: Eq2Problem, result: RegistrationResult) -> tuple[Eq2Problem, RegistrationResult]:
        for _ in range(int(params.local_rounds)):
            try:
                eq2_local = local(result.T_target_source)
            except ValueError:  # the minimiser sits away from every voxel: keep it
                break
            # GNC alone: near a minimiser most pairs are mutually consistent, and the max-clique
            # search of such a dense graph costs more than it tells (measured 0.3 s a round).
            eq2, result = eq2_local, _timed(lambda p=eq2_local.problem: solve_registration(
                p, method="gnc"))
        return eq2, result

    if params.seed_mode == "union":
        eq2 = near(T)
        return SeededEq2(np.zeros(1, dtype=np.int64), (eq2,), (solve_eq2(eq2, certify=False),),
                         np.full(1, np.nan), rounds)
    # One solve per seed; the minimisers' support: eq. (2)'s own ranking of their basins.
    found: list[tuple[int, float, Eq2Problem, RegistrationResult]] = []
    for s, start in enumerate(T):
        try:
            eq2 = near(start[None])
        except ValueError:  # this seed is near no voxel
            continue
        if s < n_full:
            result = solve_eq2(eq2, certify=False)
        else:
            result = _timed(lambda p=eq2.problem: solve_registration(p, method="gnc"))
        try:
            score = _support(local(result.T_target_source), result)
        except ValueError:
            continue
        found.append((s, score, eq2, result))
    if not found:
        raise ValueError(f"None of the {T.shape[0]} seed poses is near an occupied voxel.")
    return SeededEq2(np.array([f[0] for f in found], dtype=np.int64),
                     tuple(f[2] for f in found), tuple(f[3] for f in found),
                     np.array([f[1] for f in found]), rounds)


def _timed(solve: Any) -> RegistrationResult:
    from dataclasses import replace

    t0 = time.perf_counter()
    result = solve()
    return replace(result, info={**result.info, "registration_time": time.perf_counter() - t0,
                                 "certificate_message": "not requested"})


def _support(eq2: Eq2Problem, result: RegistrationResult) -> float:
    """Eq. (2)'s objective as a support, ``sum_ij w_ij (1 - r_ij^2 / eps^2)_+``, at ``result``'s
    pose: the higher the better; comparable between problems of the same object points whose
    candidates hold every voxel near the pose (the local rounds')."""
    p = eq2.problem
    r2 = p.residuals_sq(result.rotation, result.translation)  # already divided by eps^2
    return float(np.sum(p.weights * np.maximum(p.cbar2 - r2, 0.0)))


def _check_transforms(T: ArrayLike, name: str) -> NDArray[np.float64]:
    """``(S, 4, 4)`` rigid transforms (one ``(4, 4)`` is promoted), validated."""
    from solvers.validation import check_transform

    a = np.asarray(T, dtype=np.float64)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or a.shape[1:] != (4, 4) or a.shape[0] < 1:
        raise ValueError(f"Expected `{name}` to have shape (S, 4, 4), got {np.shape(T)}.")
    return np.stack([check_transform(t, name, atol=1e-6) for t in a])


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
    eq2: Eq2Problem, result: RegistrationResult, *, time_limit: float | None = None,
    skip_futile: bool = False,
) -> RegistrationResult:
    """Certify an eq. (2) solution with :func:`solvers.certify.certify_result` (``time_limit``
    and ``skip_futile`` are its own).

    If the certifier fails, ``result`` comes back with ``certificate=None`` and
    ``info["certificate_message"]`` says why. The certifier may return
    a better pose than ``result``'s (it then says so in its message).
    """
    from dataclasses import replace

    from solvers.certify import certify_result
    from solvers.interrupt import reraise_interrupt

    try:
        t0 = time.perf_counter()
        certified = certify_result(eq2.problem, result, time_limit=time_limit,
                                   skip_futile=skip_futile)
        result = replace(result, info={**result.info, "certify_time": time.perf_counter() - t0})
    except Exception as exc:  # a failing backend must not lose the pose
        reraise_interrupt(exc)
        msg = f"certification failed: {type(exc).__name__}: {exc}"
        log.warning("eq. (2): %s", msg)
        return replace(result, info={**result.info, "certificate_message": msg})
    return replace(certified, info={**result.info, **certified.info,
                                    "certificate_message": "certifier ran"})
