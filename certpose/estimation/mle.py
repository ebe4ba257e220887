r"""Maximum-likelihood pose: eq. (2) (see :mod:`certpose.model.eq2`) as one hypothesis, then eq. (1).

**Refinement on eq. (1).** Eq. (2) is only an approximation of eq. (1), and the descriptors
(FPFH of ``points.xyz``, or FPFH and colour of an appearance model) rarely rank the right voxel
among an object point's top-k candidates (see :mod:`certpose.model.eq2`). So eq. (2) is solved
about each of the coarse search's leading distinct hypotheses (``Eq2Params.num_seeds`` and
``gnc_seeds``: all 16 that are refined, so that whatever basin the refinement finds is an
eq. (2) minimiser's; :func:`~certpose.model.eq2.solve_eq2_about_seeds`): each minimiser replaces its seed and is
refined on eq. (1) as every hypothesis is, so that eq. (1) chooses among their basins; the one
whose minimiser climbed highest is certified (coarse-to-fine):

1. a batched coarse search of eq. (1) on a farthest-point subsample of the object: random
   rotations, each with a 3x3x3 grid of translations around the one that puts the
   camera-facing model points on the centre of the classifier's positive voxels
   (:func:`evidence_centres`: the largest cluster, not the mean, which a mask bleeding onto the
   background drags away; the other clusters are searched when every pose hides the object in
   unobserved space), and, beside them, the same rotations slid onto the positives near that
   centre (one translation each, ``coarse_align_offsets``: a partly occluded object's seen part
   lies centimetres from its facing side's centroid; positives half off the object slide them
   away, hence both); this stage uses a coarser eq. (1) whose free space is eroded next to
   surfaces (``coarse_erosion``) so that poses a voxel or two off still rank high;
2. eq. (2) about each of the best distinct hypotheses, solved; the hypotheses, the leading
   ones as their eq. (2) minimisers (``"eq2:<rank>"``), are refined on the coarse model, ranked
   on the exact eq. (1) of the whole object, and the best few and the best eq. (2) minimiser
   refined on it (all together: :func:`~certpose.estimation.batch.refine_poses`); the problem
   of the eq. (2) minimiser that climbed highest gets its local rounds (begun at its refined
   pose) and its certificate starts in a thread. Measured (``examples/benchmarks/bench_box.py
   --models appearance``, 18 cross-scene pairs): the refined eq. (2) hypothesis is the winner or
   within 0.5 cm / 2 deg of it in 17/18 pairs with the mask and 15/18 box only (7/18 and 5/18
   when one minimiser, the highest support's, was refined: with the mask it lost 11, turned
   by 150-180 degrees from the winner in 8, which eq. (2), without a free-space term, does not
   tell apart, and stalled 4-8 degrees from the winner in its basin in 3); with all 16 refined
   hypotheses seeded, 18/18 and 16/18, and 49/60 geometry-only pairs (``examples/benchmarks/bench_eq2.py``;
   39/60 with 8 seeds: the other winners came from coarse ranks 9-16);
3. local refinement stops at the first local maximum of a rough objective, often tens of nats
   below the basin's top: the best ``hop_starts`` distinct hypotheses hop on
   (:func:`~certpose.estimation.batch.basin_hop`: random perturbations refined, kept when
   better); the winner gets a derivative-free polish (a batched compass search,
   ``MLEParams.polish``), then its near-symmetric turns are tried
   (:mod:`certpose.estimation.modes`), and a better turn hops and is polished in turn; when
   the winner is not the eq. (2) minimiser being certified (a turn, or another hypothesis that
   hopped past it), eq. (2) is solved again about the winner and that one is certified (about
   a hypothesis that hopped past it right after the hops, so that the certificate runs beside
   the turns; the certification it replaces is not waited for).

Measured on 60 YCB-Video pairs (``examples/benchmarks/bench_basins.py``, geometry-only models, mask
classifier): the returned eq. (1) is within 1 nat of the locally refined ground truth, or above
it, in 60/60 pairs (59/60 with a 3x3x3 grid of offsets around each slid translation as well;
60/60 with the slid translations alone, without the unslid ones, which lost box-only pairs; 56/60
before the coarse translations slid onto the positives: the partly occluded bowl of scene 0049 in
3 frames, up to 123 nats below; 52/60 without the hops,
the batched refinement and the evidence centres; with voxel-averaged models 58/60, was 49/60). The search
is random and the eq. (2) certifier's better pose, a hypothesis, depends on its time limit, so
a pair near the threshold can change from one run to the next.

The pose with the highest eq. (1) wins. With ``MLEParams.search_points`` (off by default: it
finds fewer basins, see there) steps 2-3 climb on a farthest-point subsample of the object, and
the winner and its competing modes are then refined together on the exact eq. (1) of the whole
object and the best polished there, so every value reported is the exact eq. (1). The eq. (2)
certificate is computed in a thread beside the whole search and waited for only at its end; if
the certifier returns a better eq. (2) pose, that pose is refined as one more hypothesis (and
hops when it beats the winner). :class:`MLEResult` records where the winner came from and how
the eq. (2) pose scored on eq. (1). :func:`global_search` is the long Nevergrad search used to
judge both.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from certpose.model.eq2 import (
    Eq2Params,
    SeededEq2,
    build_eq2_problem,
    certify_eq2,
    solve_eq2,
    solve_eq2_about_seeds,
)
from solvers.lie import project_to_so3, se3_exp
from solvers.validation import check_transform, resolve_rng

if TYPE_CHECKING:
    from certpose.estimation.modes import PoseMode
    from certpose.geometry.objects import ObjectModel
    from certpose.model.classifier import ObjectClassification
    from certpose.model.grid import GridSpec
    from certpose.model.likelihood import LikelihoodParams, PoseLikelihood
    from solvers import Certificate, RegistrationResult

__all__ = [
    "MLEParams",
    "MLEResult",
    "MLEStatus",
    "Hypothesis",
    "refine_pose",
    "coarse_search",
    "evidence_centres",
    "estimate_mle",
    "global_search",
]

log = logging.getLogger(__name__)


def _twist_to_pose(T0: NDArray[np.float64], x: NDArray[np.float64], scale: float) -> NDArray[np.float64]:
    return T0 @ se3_exp(np.r_[x[:3] * scale, x[3:]])


def _twists_to_poses(T0: NDArray[np.float64], X: NDArray[np.float64], scale: float) -> NDArray[np.float64]:
    """``T0 @ [exp(omega), scale * rho]`` for each row ``[rho, omega]`` of ``X`` (a local chart
    of SE(3) around ``T0``, vectorised)."""
    from scipy.spatial.transform import Rotation

    D = np.zeros((X.shape[0], 4, 4))
    D[:, :3, :3] = Rotation.from_rotvec(X[:, 3:]).as_matrix()
    D[:, :3, 3] = X[:, :3] * scale
    D[:, 3, 3] = 1.0
    return T0 @ D


def refine_pose(
    likelihood: PoseLikelihood,
    T0: ArrayLike,
    *,
    scale: float,
    max_step: float = 0.5,
    method: str = "L-BFGS-B",
    fd_step: float = 0.02,
    maxiter: int = 200,
) -> tuple[NDArray[np.float64], float, int]:
    """Locally maximise eq. (1) from ``T0`` with a bounded scipy optimiser.

    The pose is ``T0 @ [exp(omega), rho]`` (Powell: ``T0 @ exp([rho, omega])``) with
    ``x = [rho / scale, omega]`` bounded by
    ``|x| <= max_step`` component-wise (translation in units of ``scale`` metres, rotation in
    radians), so that line searches cannot jump to another basin.

    Parameters
    ----------
    likelihood : PoseLikelihood
    T0 : (4, 4) array_like
        Starting ``T_scene_object``.
    scale : float
        Metres per unit of the translation coordinates (e.g. the object radius).
    max_step : float
        Bound on every coordinate of ``x``.
    method : {"L-BFGS-B", "Powell"}
        ``"L-BFGS-B"`` (run as scipy's BFGS with a quadratic wall at the bounds, which is
        faster here than scipy's bounded L-BFGS-B) uses central differences of step ``fd_step`` (the 12 poses of one
        gradient go to eq. (1) as one batch; the step also smooths the piecewise-linear
        objective). ``"Powell"`` is derivative-free and slower.
    fd_step : float
        Finite-difference step in ``x`` units.
    maxiter : int
        Iteration limit (for Powell: evaluation limit ``10 * maxiter``).

    Returns
    -------
    T : (4, 4) ndarray
        The refined ``T_scene_object``.
    value : float
        Eq. (1) at ``T``.
    nfev : int
        Number of eq. (1) evaluations.
    """
    from scipy.optimize import minimize

    T0 = check_transform(T0, "T0", atol=1e-3)
    T0[:3, :3] = project_to_so3(T0[:3, :3])  # e.g. float32 ground truth
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"`scale` must be positive, got {scale}.")
    if method not in ("L-BFGS-B", "Powell"):
        raise ValueError(f"`method` must be 'L-BFGS-B' or 'Powell', got {method!r}.")
    f0 = float(likelihood(T0))
    bounds = [(-max_step, max_step)] * 6
    count = [1]
    if method == "Powell":
        def neg(x: NDArray[np.float64]) -> float:
            count[0] += 1
            return -float(likelihood(_twist_to_pose(T0, x, scale)))

        res = minimize(neg, np.zeros(6), method="Powell", bounds=bounds,
                       options={"xtol": 1e-3, "ftol": 1e-7, "maxfev": 10 * int(maxiter)})
    else:
        steps = np.vstack([np.zeros(6), fd_step * np.eye(6), -fd_step * np.eye(6)])

        def fun_grad(x: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
            poses = _twists_to_poses(T0, x + steps, scale)
            v = -np.asarray(likelihood(poses))
            count[0] += len(steps)
            return float(v[0]), (v[1:7] - v[7:]) / (2.0 * fd_step)

        def penalised(x: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
            # A quadratic wall keeps BFGS inside the box (scipy's bounded L-BFGS-B costs ~1 ms
            # per iteration in its own code, more than eq. (1) here).
            over = np.abs(x) - max_step
            xc = np.clip(x, -max_step, max_step)
            v, g = fun_grad(xc)
            pen = np.where(over > 0, over, 0.0)
            return v + 1e4 * float(pen @ pen), g + 2e4 * pen * np.sign(x)

        res = minimize(penalised, np.zeros(6), jac=True, method="BFGS",
                       options={"maxiter": int(maxiter), "gtol": 1e-3})
    res.x = np.clip(res.x, -max_step, max_step)
    T = _twist_to_pose(T0, res.x, scale) if method == "Powell" else _twists_to_poses(
        T0, res.x[None], scale)[0]
    # Score the pose returned: BFGS's value includes the wall's penalty when it ended outside
    # the box, and clipping moved it.
    value = float(likelihood(T))
    count[0] += 1
    if not value > f0:  # no improvement: keep the start
        return T0, f0, count[0]
    return T, value, count[0]


def coarse_search(
    likelihood: PoseLikelihood,
    object_model: ObjectModel,
    centre: ArrayLike,
    *,
    num_rotations: int = 1024,
    offsets: ArrayLike = (-0.15, 0.0, 0.15),
    viewing_direction: ArrayLike | None = None,
    evidence: ArrayLike | None = None,
    align_iterations: int = 3,
    rng: np.random.Generator | int | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Evaluate eq. (1) on a batch of poses around ``centre``.

    Poses: ``num_rotations`` uniformly random rotations. With a ``viewing_direction`` (camera
    to ``centre``) and model normals, each rotation's translation puts the centroid of the
    model points that would face the camera on ``centre`` (the centroid of what the camera
    sees of the object); without them, the object's centroid goes on ``centre``. With
    ``evidence`` as well, each translation then slides so that the facing points fit the
    evidence (:func:`_align_translations`): when an occluder hides part of the object, the
    centroid of what is seen lies several centimetres from that of the facing side (measured:
    the YCB-Video bowl in scene 0049, 4 cm, three times the offsets' reach, so no pose near
    the truth was tried). Each translation is then shifted by ``radius * (a, b, c)`` for every
    ``a, b, c`` in ``offsets`` (a 3-D grid of translations per rotation).

    Parameters
    ----------
    likelihood : PoseLikelihood
        The eq. (1) to evaluate (callable on ``(B, 4, 4)`` poses).
    object_model : ObjectModel
        The object points (and normals) placed by the poses.
    centre : (3,) array_like
        Where the seen part of the object is, scene frame, metres.
    num_rotations : int
        Random rotations.
    offsets : array_like of float
        Translation offsets per axis, in object radii.
    viewing_direction : (3,) array_like, optional
        Camera to ``centre``.
    evidence : (M, 3) array_like, optional
        Scene points (metres) on the seen surface of the object, e.g. a sample of the
        classifier's positive voxels near ``centre``; used only with ``viewing_direction``
        and model normals.
    align_iterations : int
        Point-to-plane steps of the alignment to ``evidence`` (0: none).
    rng : numpy Generator, int or None

    Returns
    -------
    poses : (B, 4, 4) ndarray
    values : (B,) ndarray
        Eq. (1) of each pose.
    """
    from scipy.spatial.transform import Rotation

    gen = resolve_rng(rng)
    c = np.asarray(centre, dtype=np.float64).reshape(3)
    R = Rotation.random(int(num_rotations), random_state=gen).as_matrix()
    P = object_model.points
    if viewing_direction is None or object_model.normals is None:
        anchors = np.broadcast_to(object_model.centroid, (R.shape[0], 3))
    else:
        v = np.asarray(viewing_direction, dtype=np.float64).reshape(3)
        v = v / max(float(np.linalg.norm(v)), 1e-12)
        # Normal n faces the camera under R when (R n) . v < 0, i.e. n . (R^T v) < 0.
        facing = (object_model.normals @ (R.transpose(0, 2, 1) @ v).T).T < 0  # (B, N)
        count = np.maximum(facing.sum(axis=1, keepdims=True), 1)
        anchors = (facing.astype(np.float64) @ P) / count
    base = c - np.einsum("bij,bj->bi", R, anchors)  # (B, 3)
    if evidence is not None and viewing_direction is not None and object_model.normals is not None:
        E = np.asarray(evidence, dtype=np.float64)
        if E.ndim != 2 or E.shape[1] != 3:
            raise ValueError(f"Expected `evidence` to have shape (M, 3), got {E.shape}.")
        if len(E) and int(align_iterations) > 0:
            base = _align_translations(R, base, P, object_model.normals, facing, E,
                                       iterations=int(align_iterations),
                                       max_distance=object_model.radius)
    o = np.asarray(offsets, dtype=np.float64).reshape(-1) * object_model.radius
    shifts = np.stack(np.meshgrid(o, o, o, indexing="ij"), axis=-1).reshape(-1, 3)
    poses = np.zeros((R.shape[0], shifts.shape[0], 4, 4))
    poses[:, :, 3, 3] = 1.0
    poses[:, :, :3, :3] = R[:, None]
    poses[:, :, :3, 3] = base[:, None, :] + shifts[None, :, :]
    poses = poses.reshape(-1, 4, 4)
    return poses, np.asarray(likelihood(poses))


def _align_translations(R: NDArray[np.float64], t: NDArray[np.float64], P: NDArray[np.float64],
                        normals: NDArray[np.float64], facing: NDArray[np.bool_],
                        E: NDArray[np.float64], *, iterations: int,
                        max_distance: float) -> NDArray[np.float64]:
    """Translations ``t`` (B, 3) slid so that the facing model points ``R_b P`` fit ``E``.

    Translation-only point-to-plane ICP from the evidence to its nearest facing point (evidence
    to model: what is seen is a part of the model, not the other way round); pairs farther
    than ``max_distance`` are dropped. Point-to-point converges slowly along curved surfaces
    (measured: the YCB-Video bowl, 1-3 cm off after 10 steps against 0.2-0.4 cm after 3). The
    ridge term keeps directions the normals do not constrain (a flat face slides freely) at
    the anchor.
    """
    # float32 about the evidence's mean (centimetre-scale values, no cancellation): the
    # distances are the cost here, about 4M per step.
    o = E.mean(axis=0)
    Ef = (E - o).astype(np.float32)
    Rp = (P @ R.transpose(0, 2, 1)).astype(np.float32)  # (B, N, 3) model points, rotated
    Rn = normals @ R.transpose(0, 2, 1)
    e2 = (Ef * Ef).sum(axis=1)
    ridge = 0.05 * len(E) * np.eye(3)
    hidden = np.where(facing, 0.0, np.inf).astype(np.float32)[:, None, :]
    B, K = R.shape[0], len(E)
    rows = np.arange(B)[:, None]
    j = np.empty((B, K), dtype=np.intp)
    nearest = np.empty((B, K), dtype=np.float32)
    for _ in range(iterations):
        X = Rp + (t - o).astype(np.float32)[:, None, :]
        XX = (X * X).sum(axis=2)[:, None, :]
        M = -2.0 * X.transpose(0, 2, 1)
        # Squared distances (b, K, N) through batched matrix products, 64 rotations at a time:
        # the (B, K, N) array of all (16 MB) left the cache between its passes (measured:
        # 50 -> 35 ms per call, the same values).
        for s in range(0, B, 64):
            d2 = Ef @ M[s:s + 64]
            d2 += XX[s:s + 64] + hidden[s:s + 64]
            j[s:s + 64] = np.argmin(d2, axis=2)
            nearest[s:s + 64] = np.take_along_axis(d2, j[s:s + 64, :, None], axis=2)[..., 0]
        near = nearest + e2 < max_distance**2
        q = X[rows, j].astype(np.float64)  # (B, K, 3)
        n = Rn[rows, j] * near[..., None]
        r = np.einsum("bkj,bkj->bk", (Ef - q), n)
        A = n.transpose(0, 2, 1) @ n + ridge
        t = t + np.linalg.solve(A, n.transpose(0, 2, 1) @ r[..., None])[..., 0]
    return t


def evidence_centres(
    positive: ArrayLike,
    grid: GridSpec,
    *,
    radius: float,
    max_centres: int = 3,
) -> NDArray[np.float64]:
    """Where the classifier's positive voxels gather: the coarse search's translation seeds.

    The mean of all positives is not it: a mask that bleeds over the object's silhouette puts
    positives on the background far behind (measured: YCB-Video 0049/000020, tuna can, about a
    fifth of the positives 1.2 m behind it pulled the mean 26 cm off the can, and every coarse
    pose hid the can in unobserved space). Instead: the 26-connected components of ``positive``, largest first;
    from the centroid of each that lies farther than ``radius`` from the centres already
    chosen, a flat-kernel mean shift (the mean of the positives within ``radius``,
    until it settles) gathers the fragments of one object (an occluder splitting it) into one
    centre.

    Parameters
    ----------
    positive : (X, Y, Z) array_like of bool
        The classifier's positive voxels.
    grid : GridSpec
        The scene grid (voxel centres in metres).
    radius : float
        Object radius, metres.
    max_centres : int
        At most this many centres.

    Returns
    -------
    (K, 3) ndarray
        Centres, metres, scene frame, most evidence first (``K = 0`` without positives).
    """
    from scipy.ndimage import label

    pos = np.asarray(positive, dtype=bool)
    if pos.ndim != 3:
        raise ValueError(f"Expected `positive` to have shape (X, Y, Z), got {pos.shape}.")
    if not (math.isfinite(radius) and radius > 0):
        raise ValueError(f"`radius` must be positive, got {radius}.")
    if int(max_centres) < 1:
        raise ValueError(f"`max_centres` must be >= 1, got {max_centres}.")
    labels, n = label(pos, structure=np.ones((3, 3, 3), dtype=bool))
    if n == 0:
        return np.zeros((0, 3))
    idx = np.argwhere(pos)
    lab = labels[tuple(idx.T)]
    pts = grid.centres(idx)
    sizes = np.bincount(lab, minlength=n + 1)
    centres: list[NDArray[np.float64]] = []
    for comp in np.argsort(-sizes[1:], kind="stable") + 1:
        c = pts[lab == comp].mean(axis=0)
        if any(np.linalg.norm(c - o) < radius for o in centres):
            continue
        near = None
        for _ in range(10):  # until the set within the radius stops changing
            now = np.linalg.norm(pts - c, axis=1) < radius
            if near is not None and np.array_equal(now, near):
                break
            near = now
            c = pts[near].mean(axis=0)
        centres.append(c)
        if len(centres) == int(max_centres):
            break
    return np.stack(centres)


class MLEStatus(str, Enum):
    """Outcome of :func:`estimate_mle`."""

    CONVERGED = "converged"
    """A pose maximising eq. (1) locally, best of the hypotheses tried."""
    NO_OBJECT_EVIDENCE = "no_object_evidence"
    """The classifier marked no voxel as the object: there is nothing to localise."""
    LITTLE_EVIDENCE = "little_evidence"
    """The classifier marked fewer than :data:`LITTLE_EVIDENCE` voxels per model point as the
    object: the search ran and its pose is returned, but it rests on too little to trust (a
    5-pixel box: 2 voxels for 2,288 points, a pose 43 cm off)."""
    UNEXPLAINED = "unexplained"
    """The returned pose leaves most of the classifier's evidence unexplained: fewer than
    :data:`EXPLAINED` (by classifier) of the positive voxels lie within :data:`EXPLAIN_DISTANCE`
    of the posed model (:func:`explained_fraction`). The pose is returned, not trusted."""

    @property
    def success(self) -> bool:
        return self is MLEStatus.CONVERGED


@dataclass(frozen=True)
class MLEParams:
    """Search and refinement settings of :func:`estimate_mle`.

    Attributes
    ----------
    eq2 : Eq2Params
        Construction of eq. (2).
    certify : bool
        Certify the eq. (2) solution.
    certify_time_limit : float or None
        Seconds allowed to the certifier.
    num_rotations : int
        Rotations of the batched coarse search on eq. (1) (0 disables it).
    offsets : tuple of float
        Translation offsets per axis, in object radii, of the coarse search (see
        :func:`coarse_search`).
    coarse_points : int
        Object points (farthest-point sample) used by the coarse search and the first
        refinement.
    coarse_erosion : int
        ``free_space_erosion`` (voxels) of the coarse eq. (1) used by the coarse search and the
        first refinement: free space next to surfaces is not penalised there, so poses a voxel
        or two off still rank high (measured: the right basin of the YCB-Video mug ranks about
        500th of 27k coarse poses with 0, in the top 3 with 3).
    num_refine_coarse : int
        Hypotheses refined on the subsampled object.
    num_refine_fine : int
        Of those, the best (on the exact eq. (1) of the whole object) refined again on the
        whole object; the best eq. (2) minimiser always is.
    coarse_maxiter : int
        Iteration limit of each refinement on the subsampled object.
    refine_maxiter : int
        Iteration limit of each refinement on the whole object (see :func:`refine_pose`).
    explore_modes : bool
        Try the winner's near-symmetric turns (:func:`~certpose.estimation.modes.explore_modes`:
        the 180-degree flips of boxes and cans, where the coarse search misses basins); a turn
        that scores better on eq. (1) becomes the winner.
    ring_modes : bool
        For an object with an axis of revolution, also report the poses of its ring (turns
        about the axis every 15 deg, upright and upside down) that score within the window
        after a short climb, the best few just outside it polished and their gain credited to
        the ring's other samples (:func:`~certpose.estimation.modes.revolution_turns`,
        :data:`RING_POLISH`): a can's or a hidden-handle mug's continuous ambiguity as a set of
        modes.
    mode_window : float
        Local maxima of eq. (1) within this many tempered nats of the best are reported as
        competing modes (:attr:`MLEResult.modes`): nats of eq. (1) divided by the sampler's
        default temperature at the best pose
        (:func:`~certpose.sampling.sampler.default_temperature`, about 11 on YCB-Video's
        objects), the units in which the pose distribution weighs them. Eq. (1)'s scatter
        between the symmetric poses of a symmetric shape is of that order (a box's flips 7-47
        nats below the best on the shared YCB-Video frames, geometry-only models).
    mode_refine : int
        Near-symmetric turns refined on the exact eq. (1) (the best after pre-refinement on the
        coarse one; ``num_refine`` of :func:`~certpose.estimation.modes.explore_modes`). 6 missed
        the potted-meat can's basin in YCB-Video 0002/000020 with an appearance model from 0049
        (the returned pose 90 nats below the refined truth, depending on the coarse subsample).
    hop_rounds : int
        Rounds of :func:`~certpose.estimation.batch.basin_hop` from the best hypotheses (0
        disables it).
    hop_starts : int
        Distinct hypotheses (best first) that hop (measured: the banana in 0050/000001 reaches
        the truth's basin from the second best, 21 degrees off, and not from the best).
    hop_samples : int
        Perturbed poses per start and round (refined on the subsampled object; the best 4 of
        them on the whole object).
    hop_translation : float
        Standard deviation of the perturbations' translation per axis, in object radii.
    hop_rotation_deg : float
        Standard deviation of the perturbations' rotation vector per axis, degrees.
    hop_drop_behind : float
        A start that trails the best one by more than this many nats after a round stops
        hopping (``drop_behind`` of :func:`~certpose.estimation.batch.basin_hop`). Measured on
        the 60 pairs of ``examples/benchmarks/bench_basins.py``: the second start won in 5 pairs, each
        time ahead after the first round already; of those behind, none came closer than
        1.8 nats (the banana, 0050, from 13.9 behind); the cut spares 16% of the hops'
        eq. (1) terms.
    coarse_align_iterations : int
        Point-to-plane steps that slide each coarse translation so that the model points facing
        the camera fit the classifier's positives near the centre (see :func:`coarse_search`),
        tried beside the unslid translations (0: those only). Measured
        (``examples/benchmarks/bench_basins.py``): the bowl in scene 0049, partly occluded, is found in
        3 of 3 frames instead of 0.
    coarse_align_offsets : tuple of float
        Translation offsets per axis, in object radii, around each slid translation (the
        unslid ones keep ``offsets``). The slide puts the facing points on the evidence to a
        few millimetres (the bowl: 0.2-0.4 cm), which the refinement recovers, so by default
        the slid translation alone is tried (1 pose per rotation, not 27: 28k coarse poses
        instead of 55k). Measured side by side with the 3x3x3 grid
        (``examples/benchmarks/bench_basins.py``, 60 pairs): basins 60/60 against 59/60 (the bowl
        0049/000001 now found); ``examples/benchmarks/bench_box.py --models appearance`` unchanged
        (mask and box only: ADD-S 18/18, right 15/18, basins 18/18).
    coarse_align_points : int
        Positives (an even sample of those within an object diameter of the centre) that the
        alignment fits.
    num_centres : int
        Clusters of the classifier's positives (:func:`evidence_centres`) the coarse search may
        start from: the largest first, the others when every pose found hides the object.
    search_points : int or None
        Object points (farthest-point sample, area-weighted like the whole model) of the eq. (1)
        that the refinement, the basin hops and the turns climb on; the winner and its modes are
        then refined and polished on the whole object (``None``, the default: the whole object
        throughout). Measured (``examples/benchmarks/bench_basins.py``, 60 YCB-Video pairs, side by side
        with the whole object): 1024 cuts the median MLE time by about a quarter (6.4 s against
        8.8 s at load 2-9) but finds fewer basins (55/60 against 57/60: the banana and the
        mustard bottle of scene 0050 climb to other maxima on the subsample), 768 gave 54/60.
    polish : {"compass", "powell"}
        The last, derivative-free climb of the winner: a batched compass search
        (:func:`~certpose.estimation.batch.polish_poses`, 12 poses per eq. (1) call) or scipy's
        Powell (one pose per call; about ten times slower here).
    """

    eq2: Eq2Params = field(default_factory=Eq2Params)
    certify: bool = True
    certify_time_limit: float | None = 1.0
    num_rotations: int = 1024
    offsets: tuple[float, ...] = (-0.15, 0.0, 0.15)
    coarse_points: int = 128
    coarse_erosion: int = 3
    num_refine_coarse: int = 16
    num_refine_fine: int = 3
    coarse_maxiter: int = 30
    refine_maxiter: int = 60
    explore_modes: bool = True
    ring_modes: bool = True
    mode_window: float = 5.0
    mode_refine: int = 12
    hop_rounds: int = 3
    hop_starts: int = 2
    hop_samples: int = 32
    hop_translation: float = 0.08
    hop_rotation_deg: float = 8.0
    hop_drop_behind: float = 30.0
    coarse_align_iterations: int = 3
    coarse_align_offsets: tuple[float, ...] = (0.0,)
    coarse_align_points: int = 32
    num_centres: int = 3
    search_points: int | None = None
    polish: str = "compass"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.mode_window) and self.mode_window >= 0):
            raise ValueError(f"`mode_window` must be >= 0 tempered nats, got {self.mode_window}.")
        if int(self.num_rotations) < 0:
            raise ValueError(f"`num_rotations` must be >= 0, got {self.num_rotations}.")
        if int(self.coarse_points) < 3:
            raise ValueError(f"`coarse_points` must be >= 3, got {self.coarse_points}.")
        if int(self.num_refine_coarse) < 1 or int(self.num_refine_fine) < 1:
            raise ValueError("`num_refine_coarse` and `num_refine_fine` must be >= 1.")
        if int(self.refine_maxiter) < 1 or int(self.coarse_maxiter) < 1:
            raise ValueError("`refine_maxiter` and `coarse_maxiter` must be >= 1.")
        if int(self.hop_rounds) < 0 or int(self.hop_samples) < 1 or int(self.hop_starts) < 1:
            raise ValueError(f"`hop_rounds` must be >= 0, `hop_samples` and `hop_starts` >= 1, "
                             f"got {self.hop_rounds}, {self.hop_samples} and {self.hop_starts}.")
        if not self.hop_drop_behind >= 0:
            raise ValueError(f"`hop_drop_behind` must be >= 0 nats, got {self.hop_drop_behind}.")
        if not (self.hop_translation >= 0 and self.hop_rotation_deg >= 0):
            raise ValueError(f"`hop_translation` and `hop_rotation_deg` must be >= 0, got "
                             f"{self.hop_translation} and {self.hop_rotation_deg}.")
        if int(self.coarse_align_iterations) < 0 or int(self.coarse_align_points) < 1:
            raise ValueError(f"`coarse_align_iterations` must be >= 0 and `coarse_align_points` "
                             f">= 1, got {self.coarse_align_iterations} and "
                             f"{self.coarse_align_points}.")
        if int(self.mode_refine) < 1:
            raise ValueError(f"`mode_refine` must be >= 1, got {self.mode_refine}.")
        if int(self.num_centres) < 1:
            raise ValueError(f"`num_centres` must be >= 1, got {self.num_centres}.")
        if self.polish not in ("compass", "powell"):
            raise ValueError(f"`polish` must be 'compass' or 'powell', got {self.polish!r}.")
        if self.search_points is not None and int(self.search_points) < 3:
            raise ValueError(f"`search_points` must be >= 3 or None, got {self.search_points}.")


@dataclass(frozen=True, eq=False)
class MLEResult:
    """The maximum-likelihood pose.

    Attributes
    ----------
    T_scene_object : (4, 4) ndarray
        Maps object-model points into the scene frame.
    log_likelihood : float
        Eq. (1) at ``T_scene_object`` (nats, up to ``-N log Z``).
    hypothesis : str
        Where the winning pose came from: ``"eq2:<rank>"`` (the eq. (2) minimiser about the
        coarse search's hypothesis of that rank, refined), ``"eq2"`` (the descriptor problem's
        minimiser, or the certifier's better pose, refined), ``"coarse:<rank>"`` (the coarse
        search) or ``"turn:<k>"`` (a near-symmetric turn of the search's winner).
    eq2_result : RegistrationResult or None
        The eq. (2) solve (``T_target_source`` = its pose), with its certificate: the local
        rounds begun where the minimiser that climbed highest on eq. (1) ended, or at the
        returned pose when that descends from another hypothesis (e.g. a near-symmetric turn).
    eq2_log_likelihood : float
        Eq. (1) at the eq. (2) pose, before refinement (``nan`` without a solve).
    eq2_refined_log_likelihood : float
        Eq. (1) of the best refined eq. (2) minimiser (``nan`` without a solve).
    certificate : Certificate or None
        Certificate of the eq. (2) solution (it bounds eq. (2), not eq. (1)).
    num_evaluations : int
        Eq. (1) evaluations spent.
    timings : dict of str to float
        Seconds per stage; the certifier (``eq2_certify``) runs in a thread beside the whole
        search, ``eq2_certify_wait`` is the time spent waiting for it at the search's end
        (``refine_exact``: the final refinement on the whole object, when the search climbed on
        a subsample).
    status : MLEStatus
    message : str
    hypotheses : tuple of Hypothesis
        The hypotheses as refined by the search (before the hops and the winner's polish), each
        scored on the exact eq. (1).
    modes : tuple of PoseMode
        Local maxima of eq. (1) within ``mode_window`` tempered nats of the best, best first (the
        returned pose first); more than one means eq. (1) barely tells them apart (e.g. a box's
        flips without appearance).
    eq2_problem : Eq2Problem or None
        The eq. (2) problem that was solved (scene frame; ``certpose pose --save-problem``).
    """

    T_scene_object: NDArray[np.float64]
    log_likelihood: float
    hypothesis: str
    eq2_result: RegistrationResult | None
    eq2_log_likelihood: float
    eq2_refined_log_likelihood: float
    certificate: Certificate | None
    num_evaluations: int
    timings: dict[str, float]
    status: MLEStatus
    message: str
    hypotheses: tuple[Hypothesis, ...] = ()
    modes: tuple[PoseMode, ...] = ()
    eq2_problem: Any = field(default=None, repr=False)

    @property
    def success(self) -> bool:
        return self.status.success

    @property
    def pose_is_certified(self) -> bool:
        """Whether :attr:`certificate` certifies :attr:`T_scene_object` itself.

        The certificate bounds eq. (2) at the eq. (2) minimiser; the returned pose maximises
        eq. (1) and is refined away from it (even when it started there), so this is False
        unless the returned pose is that minimiser.
        """
        return (self.certificate is not None and bool(self.certificate.certified)
                and self.eq2_result is not None
                and np.allclose(self.T_scene_object, self.eq2_result.T_target_source, atol=1e-9))

    def certificate_scope(self) -> str:
        """One line: what the certificate bounds, its verdict, and whether it covers the pose."""
        if self.certificate is None:
            why = "" if self.eq2_result is None else str(
                self.eq2_result.info.get("certificate_message", ""))
            return f"no certificate{': ' + why if why else ''}; eq. (1), which the pose maximises, has none"
        c = self.certificate
        verdict = "CERTIFIED globally optimal" if c.certified else f"not certified ({c.status.value})"
        if self.pose_is_certified:
            covers = "it covers the returned pose"
        elif c.certified:
            covers = ("it covers the eq. (2) minimiser, NOT the returned pose (which maximises "
                      f"eq. (1), winner {self.hypothesis}; no certificate bounds eq. (1))")
        else:
            covers = (f"no pose is certified, the returned one (winner {self.hypothesis}, which "
                      "maximises eq. (1)) neither")
        bound = ("" if c.certified or not np.isfinite(c.lower_bound) else
                 f", its cost {c.upper_bound:.6g} at most {c.upper_bound - c.lower_bound:.4g} above the "
                 f"optimum")
        return (f"eq. (2) minimiser {verdict} for the problem {c.problem} ({c.num_terms} TLS terms, "
                f"gap {c.relative_gap:.3g}{bound}); {covers}")


def _distinct_top(poses: NDArray[np.float64], values: NDArray[np.float64], m: int,
                  min_dist: float, min_angle: float) -> list[int]:
    """Indices of the ``m`` best poses, skipping near-duplicates of better ones."""
    order = np.argsort(-values)
    chosen: list[int] = []
    for i in order:
        ok = True
        for j in chosen:
            dt = np.linalg.norm(poses[i, :3, 3] - poses[j, :3, 3])
            cos = (np.trace(poses[i, :3, :3].T @ poses[j, :3, :3]) - 1.0) / 2.0
            if dt < min_dist and cos > math.cos(min_angle):
                ok = False
                break
        if ok:
            chosen.append(int(i))
        if len(chosen) == m:
            break
    return chosen


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """One candidate pose of :func:`estimate_mle` and how it scores.

    Attributes
    ----------
    pose : (4, 4) ndarray
        ``T_scene_object``.
    score : float
        Eq. (1) at ``pose`` on the likelihood of the step that produced it (nats; ``nan`` when
        not scored yet).
    source : str
        ``"eq2"``, ``"eq2:<rank>"``, ``"coarse:<rank>"``, ``"centroid"`` or ``"turn:<k>"``.
    """

    pose: NDArray[np.float64]
    score: float
    source: str


class _Certifier:
    """The eq. (2) certifier in a worker thread beside the eq. (1) search (a context manager).

    The certifier (cvxpy/clarabel, scipy) runs while eq. (1) is searched, which releases the GIL
    in its numba kernels, so on 2 cores the two overlap. A problem submitted replaces the one
    before without waiting for it: a certification already running goes on in its thread (it
    cannot be interrupted) while the search goes on, and its result is dropped. Leaving the
    ``with`` block, normally or by an exception, shuts every pool down and waits for their
    threads (the time limit bounds the wait), so no certifier outlives the call.
    """

    THREAD_PREFIX = "certpose-eq2-certify"

    def __init__(self) -> None:
        self._pool: Any = None
        self._future: Any = None
        self._replaced: list[Any] = []

    def __enter__(self) -> _Certifier:
        return self

    def __exit__(self, *exc: object) -> None:
        if self._pool is not None:
            if self._future is not None:
                self._future.cancel()
            self._replaced.append(self._pool)
            self._pool = None
        for pool in self._replaced:
            pool.shutdown(wait=True, cancel_futures=True)
        self._replaced = []

    def submit(self, eq2: Any, result: RegistrationResult, time_limit: float | None) -> None:
        from concurrent.futures import ThreadPoolExecutor

        if self._pool is not None:  # a new problem replaces the one submitted before
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._replaced.append(self._pool)
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=self.THREAD_PREFIX)
        # Only a certificate is of use here, not a bound that cannot certify: the clique-number
        # bound of real frames' eq. (2) never could (best possible gap 0.99) and its search
        # took 0.01-0.4 s of a core the eq. (1) kernels use.
        self._future = self._pool.submit(certify_eq2, eq2, result, time_limit=time_limit,
                                         skip_futile=True)

    @property
    def running(self) -> bool:
        return self._future is not None

    def result(self) -> RegistrationResult:
        return self._future.result()


@dataclass
class _Search:
    """State shared by the steps of :func:`estimate_mle`: ``exact`` is eq. (1) of the whole
    object, ``full`` the one the search climbs on (the whole object, or a subsample of
    ``MLEParams.search_points``), ``small`` the coarse one."""

    exact: PoseLikelihood
    full: PoseLikelihood
    small: PoseLikelihood
    small_model: ObjectModel
    scale: float
    params: MLEParams
    timings: dict[str, float] = field(default_factory=dict)
    n_eval: int = 0

    def refine(self, likelihood: PoseLikelihood, T0: NDArray[np.float64], **kw: Any) -> tuple[NDArray[np.float64], float]:
        T, v, nf = refine_pose(likelihood, T0, scale=self.scale, **kw)
        self.n_eval += nf
        return T, v

    def counted(self, likelihood: PoseLikelihood) -> Any:
        """``likelihood`` as a callable that adds the poses it scores to :attr:`n_eval`."""
        def call(T: ArrayLike) -> Any:
            out = likelihood(T)
            self.n_eval += int(np.size(out))
            return out

        call.centroid = likelihood.centroid  # type: ignore[attr-defined]
        return call


def _build_likelihoods(scene: Any, classification: ObjectClassification, object_model: ObjectModel,
                       params: MLEParams, lparams: LikelihoodParams,
                       gen: np.random.Generator) -> _Search:
    """Step 0: the exact eq. (1) and the coarse one (object subsample, eroded free space)."""
    from dataclasses import replace

    from certpose.model.likelihood import PoseLikelihood

    t = time.perf_counter()
    exact = PoseLikelihood(scene, classification, object_model, params=lparams)
    full, search_model = exact, object_model
    if params.search_points is not None and len(object_model) > int(params.search_points):
        search_model = object_model.subsample(int(params.search_points), rng=gen)
        full = exact.with_object(search_model)
    # Farthest points of the search's subsample: as even, and cheaper to draw.
    small_model = search_model.subsample(int(params.coarse_points), rng=gen)
    # The coarse search reads free space from the voxel grid, eroded: a tolerant, cheap eq. (1)
    # whose basins lead the refinement to the exact one's. With the exact eq. (1)'s per-pixel
    # free space instead, box only (best buddies), the mustard bottle in 0050/000020 (model from
    # 0002's views) ended 8 cm off at -2334 nats where its flip at the right place scores -1987.
    small = exact.with_object(small_model,
                              params=replace(lparams, free_space="voxels",
                                             free_space_erosion=int(params.coarse_erosion)))
    search = _Search(exact, full, small, small_model, object_model.radius, params)
    search.timings["compile"] = time.perf_counter() - t
    return search


def _eq2_hypotheses(search: _Search, scene: Any, classification: ObjectClassification,
                    object_model: ObjectModel, lparams: LikelihoodParams, gen: np.random.Generator,
                    certifier: _Certifier, coarse: list[Hypothesis]
                    ) -> tuple[SeededEq2 | None, Any, RegistrationResult | None, list[Hypothesis]]:
    """Step 2: eq. (2), the certifiable approximation, about each of the coarse search's leading
    hypotheses (by descriptor without them), solved.

    Returns the seeded problems (``None`` for the descriptor problem), the problem and minimiser
    to certify when known now (the descriptor problem's: its certifier is started; the seeded
    one's is chosen after the refinement, :func:`_certify_seeded`), and the hypotheses that go
    on to the refinement: ``coarse`` with each seed replaced by its own eq. (2) minimiser (source
    ``"eq2:<rank>"``; a seed near no voxel stays), or the descriptor problem's minimiser
    (``"eq2"``) before ``coarse``.
    """
    params = search.params
    t = time.perf_counter()
    seeded, eq2, result = None, None, None
    try:
        if coarse and params.eq2.num_seeds > 0:
            seeded = solve_eq2_about_seeds(scene, classification, object_model,
                                           np.stack([h.pose for h in coarse]), params=params.eq2,
                                           likelihood_params=lparams, rng=gen)
            hyps = list(coarse)
            for row, T in zip(seeded.seed_rows, seeded.minimisers, strict=True):
                hyps[row] = Hypothesis(T, float("nan"), f"eq2:{coarse[row].source.split(':')[1]}")
        else:
            eq2 = build_eq2_problem(scene, classification, object_model, params=params.eq2,
                                    likelihood_params=lparams, rng=gen)
            result = solve_eq2(eq2, certify=False)
            hyps = [Hypothesis(result.T_target_source, float("nan"), "eq2"), *coarse]
    except ValueError as exc:
        log.warning("eq. (2) skipped: %s", exc)
        search.timings["eq2_solve"] = time.perf_counter() - t
        return None, None, None, list(coarse)
    search.timings["eq2_solve"] = time.perf_counter() - t
    if result is not None and params.certify:
        certifier.submit(eq2, result, params.certify_time_limit)
    return seeded, eq2, result, hyps


def _certify_seeded(search: _Search, seeded: SeededEq2, finals: list[Hypothesis],
                    certifier: _Certifier, about: Hypothesis | None = None
                    ) -> tuple[Any, RegistrationResult, str | None]:
    """Step 2's end: of the seeded eq. (2) problems, the one whose minimiser climbed highest on
    eq. (1) (eq. (2)'s highest support when none was refined) gets its local rounds, begun at
    its refined pose, and its certifier is started; returns that problem and minimiser, and the
    source of the hypothesis the rounds began at (``None``: at the raw minimiser).

    ``about``: begin the rounds at this hypothesis instead (step 6's end: the winner, when it
    is not the minimiser certified; its certifier replaces the one running).

    Begun at the raw minimiser, the rounds stayed in its basin, 1-2 cm and tens of degrees from
    where eq. (1) took it (the mustard bottle, box only, in 0050/000001 and 000020: raw ADD-S
    1.01 and 1.06 cm, 0.56 and 0.36 cm begun at the refined pose).

    Eq. (2)'s support, without a free-space term, often prefers a can's or a banana's
    180-degree turn that eq. (1) rejects (8 of the 18 pairs of ``examples/benchmarks/bench_box.py``): the
    certified minimiser is then not in the basin of the returned pose."""
    t = time.perf_counter()
    refined = [h for h in finals if h.source.startswith("eq2:")]
    i, start = seeded.best_supported, about
    if about is None and refined:
        start = max(refined, key=lambda h: h.score)
    if start is not None and start.source.startswith("eq2:"):
        rows = np.flatnonzero(seeded.seed_rows == int(start.source.split(":")[1]))
        i = int(rows[0]) if rows.size else i
    # The local rounds from the minimiser as refined: eq. (2)'s minimiser in the basin that
    # eq. (1) chose (from the raw minimiser they stay in its own, often 1-2 cm away).
    eq2, result = seeded.local_rounds(i, None if start is None else start.pose)
    search.timings["eq2_solve"] = search.timings.get("eq2_solve", 0.0) + time.perf_counter() - t
    if search.params.certify:
        certifier.submit(eq2, result, search.params.certify_time_limit)
    return eq2, result, None if start is None else start.source


def _is_eq2(h: Hypothesis) -> bool:
    """Whether ``h`` descends from an eq. (2) minimiser (``"eq2"`` or ``"eq2:<rank>"``)."""
    return h.source == "eq2" or h.source.startswith("eq2:")


def _coarse_hypotheses(search: _Search, centre: NDArray[np.float64],
                       view: NDArray[np.float64] | None, gen: np.random.Generator,
                       positives: NDArray[np.float64] | None = None) -> list[Hypothesis]:
    """Step 1: the batched coarse search of eq. (1) around the classifier's positives
    (``positives``: their voxel centres, which the translations are aligned to)."""
    params = search.params
    if params.num_rotations <= 0:
        return []
    t = time.perf_counter()
    evidence = None
    if positives is not None and params.coarse_align_iterations > 0:
        # Those within an object diameter of the centre (one object, not a mask's bleed), an
        # even sample in raster order (no draw from `gen`).
        near = positives[np.linalg.norm(positives - centre, axis=1) < 2.0 * search.scale]
        k = int(params.coarse_align_points)
        evidence = near if len(near) <= k else near[np.linspace(0, len(near) - 1, k).astype(int)]
    state = gen.bit_generator.state
    poses, values = coarse_search(search.small, search.small_model, centre,
                                  num_rotations=params.num_rotations, offsets=params.offsets,
                                  viewing_direction=view, rng=gen)
    if evidence is not None and len(evidence):
        gen.bit_generator.state = state  # the same rotations, aligned
        # The aligned translations are proposals beside the anchored ones, not replacements:
        # a classifier whose positives are half off the object (best buddies in a box, precision
        # 0.5) slides them away (measured: the mustard bottle, box only, 0002/000010, returned
        # 991 nats below the refined truth with the alignment alone).
        aligned, v_aligned = coarse_search(
            search.small, search.small_model, centre, num_rotations=params.num_rotations,
            offsets=params.coarse_align_offsets, viewing_direction=view, evidence=evidence,
            align_iterations=params.coarse_align_iterations, rng=gen)
        poses, values = np.concatenate([poses, aligned]), np.concatenate([values, v_aligned])
    search.n_eval += values.size
    top = _distinct_top(poses, values, params.num_refine_coarse, 0.5 * search.scale,
                        math.radians(20))
    search.timings["coarse_search"] = time.perf_counter() - t
    return [Hypothesis(poses[i], float(values[i]), f"coarse:{r}") for r, i in enumerate(top)]


def _refine_hypotheses(search: _Search, hyps: list[Hypothesis]) -> list[Hypothesis]:
    """Step 3: refine every hypothesis on the coarse eq. (1), rank them on the exact one, and
    refine the best few (and the eq. (2) one) on it; all hypotheses climb together
    (:func:`~certpose.estimation.batch.refine_poses`, one batched eq. (1) call per iteration)."""
    from certpose.estimation.batch import refine_poses

    params = search.params
    hyps = hyps[: params.num_refine_coarse + 1]
    if not hyps:
        return []
    t = time.perf_counter()
    coarse, _ = refine_poses(search.counted(search.small), np.stack([h.pose for h in hyps]),
                             scale=search.scale, max_iter=params.coarse_maxiter)
    # Rank on the exact eq. (1) of the whole object: the coarse (eroded) model can prefer a
    # wrong mode (measured: an upside-down synthetic mug).
    exact = np.asarray(search.counted(search.full)(coarse))
    order = [int(i) for i in np.argsort(-exact, kind="stable")]
    # The best few, and the best eq. (2) minimiser (the one the certifier's pose competes with).
    fine = order[: params.num_refine_fine]
    fine += [i for i in order if _is_eq2(hyps[i]) and i not in fine][:1]
    T2, v2 = refine_poses(search.counted(search.full), coarse[fine], scale=search.scale,
                          max_iter=params.refine_maxiter, max_step=0.1)
    search.timings["refine"] = search.timings.get("refine", 0.0) + time.perf_counter() - t
    return [Hypothesis(T2[k], float(v2[k]), hyps[i].source) for k, i in enumerate(fine)]


def _hop(search: _Search, hyps: list[Hypothesis], gen: np.random.Generator) -> Hypothesis:
    """Step 5: past the local maxima next to the best ``hop_starts`` hypotheses
    (:func:`~certpose.estimation.batch.basin_hop`; measured on YCB-Video: the banana in
    0050/000001 climbs 53 nats from a maximum 13 degrees off, the potted-meat can in
    0002/000020 10 nats); returns the best."""
    from certpose.estimation.batch import basin_hop

    params = search.params
    top = _distinct_top(np.stack([h.pose for h in hyps]), np.array([h.score for h in hyps]),
                        params.hop_starts, 0.5 * search.scale, math.radians(20))
    hyps = [hyps[i] for i in top]
    if params.hop_rounds <= 0:
        return hyps[0]
    t = time.perf_counter()
    T, v = basin_hop(search.counted(search.full), np.stack([h.pose for h in hyps]),
                     scale=search.scale, coarse_likelihood=search.counted(search.small),
                     rounds=params.hop_rounds, samples=params.hop_samples,
                     translation=params.hop_translation, rotation_deg=params.hop_rotation_deg,
                     drop_behind=params.hop_drop_behind, rng=gen)
    search.timings["hop"] = search.timings.get("hop", 0.0) + time.perf_counter() - t
    i = int(np.argmax(v))
    return Hypothesis(T[i], float(v[i]), hyps[i].source) if v[i] > hyps[i].score else hyps[i]


def _polish(search: _Search, best: Hypothesis) -> Hypothesis:
    """Step 5: derivative-free polish of the winner (the finite-difference gradient stalls on
    the piecewise-linear objective near the optimum)."""
    t = time.perf_counter()
    if search.params.polish == "compass":
        from certpose.estimation.batch import polish_poses

        Ts, vs, n = polish_poses(search.exact, best.pose, scale=search.scale)
        search.n_eval += n
        T, v = Ts[0], float(vs[0])
    else:
        T, v = search.refine(search.exact, best.pose, max_step=0.05, method="Powell",
                             maxiter=search.params.refine_maxiter)
    search.timings["polish"] = search.timings.get("polish", 0.0) + time.perf_counter() - t
    return Hypothesis(T, v, best.source)


def _polish_all(search: _Search, hyps: list[Hypothesis]) -> list[Hypothesis]:
    """:func:`_polish` of each of ``hyps``; the compass searches run together (one batched
    eq. (1) call per iteration for all of them: each pose's search is the one it would run
    alone)."""
    if search.params.polish != "compass" or len(hyps) <= 1:
        return [_polish(search, h) for h in hyps]
    from certpose.estimation.batch import polish_poses

    t = time.perf_counter()
    Ts, vs, n = polish_poses(search.exact, np.stack([h.pose for h in hyps]), scale=search.scale)
    search.n_eval += n
    search.timings["polish"] = search.timings.get("polish", 0.0) + time.perf_counter() - t
    return [Hypothesis(T, float(v), h.source) for T, v, h in zip(Ts, vs, hyps, strict=True)]


def _finish(search: _Search, best: Hypothesis,
            modes: tuple[PoseMode, ...]) -> tuple[Hypothesis, tuple[PoseMode, ...]]:
    """Step 7: the winner and the competing modes refined on the exact eq. (1) (all together,
    when the search climbed on a subsample), the best of them polished; the modes within
    ``mode_window`` of it are reported, the returned pose first."""
    from certpose.estimation.batch import refine_poses
    from certpose.estimation.modes import PoseMode, _angle_deg

    params = search.params

    def distinct(T: NDArray[np.float64], kept: list[NDArray[np.float64]]) -> bool:
        return not any(_angle_deg(T[:3, :3], K[:3, :3]) < 10.0
                       and np.linalg.norm(T[:3, 3] - K[:3, 3]) < 0.5 * search.scale for K in kept)

    others: list[PoseMode] = []
    for m in modes:
        if distinct(m.T_scene_object, [best.pose] + [o.T_scene_object for o in others]):
            others.append(m)
    if search.full is not search.exact:
        t = time.perf_counter()
        T, v = refine_poses(search.counted(search.exact),
                            np.stack([best.pose] + [m.T_scene_object for m in others]),
                            scale=search.scale, max_iter=params.refine_maxiter, max_step=0.1)
        search.timings["refine_exact"] = time.perf_counter() - t
        cands = [Hypothesis(T[0], float(v[0]), best.source)] + [
            Hypothesis(T[k + 1], float(v[k + 1]), m.origin) for k, m in enumerate(others)]
        cands.sort(key=lambda h: -h.score)
        best, others_h = cands[0], []
        for h in cands[1:]:  # two modes may have climbed to one
            if distinct(h.pose, [best.pose] + [o.pose for o in others_h]):
                others_h.append(h)
    else:
        others_h = [Hypothesis(m.T_scene_object, float(m.log_likelihood), m.origin)
                    for m in others]
    best = _polish(search, best)
    # Modes just outside the window are polished as the winner was, so that the window compares
    # peaks with peaks (the mustard bottle's flip in YCB-Video 0050/000001 stalled 6.3 nats
    # below the polished winner; its peak is 4.0 below, and the truth's, refined from the truth,
    # 4.9). Those inside are reported anyway: no polish (about 0.3 s each) to decide it.
    w = _window(search, best.pose)
    # The ring's poses (an axis of revolution) are samples of a flat ridge: a polish costs about
    # 0.3 s each (9 s for a can's ring), so only the RING_POLISH best of each ring (upright,
    # upside down) just outside the window are polished, and what they gained is credited to
    # that ring's other samples (unpolished, they stand lower on the same ridge).
    band = [h for h in others_h if best.score - 2 * w <= h.score < best.score - w]
    polish = {id(h) for h in band if not h.source.startswith("ring")}
    for kind in ("ring:", "ring-flip:"):
        ring_band = sorted((h for h in band if h.source.startswith(kind)), key=lambda h: -h.score)
        polish |= {id(h) for h in ring_band[:RING_POLISH]}
    chosen = [h for h in others_h if id(h) in polish]
    polished = dict(zip(map(id, chosen), _polish_all(search, chosen), strict=True))
    near, gain = [], {"ring:": 0.0, "ring-flip:": 0.0}
    for h in others_h:
        if id(h) in polished:
            p = polished[id(h)]
            for kind in gain:
                if h.source.startswith(kind):
                    gain[kind] = max(gain[kind], p.score - h.score)
            h = p
        near.append(h)

    def credit(h: Hypothesis) -> float:
        return next((g for kind, g in gain.items() if h.source.startswith(kind)), 0.0)

    kept = [PoseMode(best.pose, best.score, best.source)] + [
        PoseMode(h.pose, h.score, h.source, _angle_deg(h.pose[:3, :3], best.pose[:3, :3]))
        for h in sorted(near, key=lambda h: -h.score) if h.score + credit(h) >= best.score - w]
    return best, tuple(kept)


#: Ring poses just outside the modes' window that :func:`estimate_mle` polishes (the best first).
RING_POLISH = 4


def _window(search: _Search, T: NDArray[np.float64]) -> float:
    """``mode_window`` in nats of eq. (1): times the sampler's default temperature at ``T``."""
    from certpose.sampling.sampler import default_temperature

    return search.params.mode_window * max(1.0, default_temperature(search.exact, T))


def _modes(search: _Search, best: Hypothesis, object_model: ObjectModel) -> tuple[Hypothesis, tuple[PoseMode, ...]]:
    """Step 6: the winner's near-symmetric turns; a better one wins, those within the window
    are reported."""
    from certpose.estimation.modes import PoseMode, explore_modes

    params = search.params
    if not params.explore_modes:
        return best, (PoseMode(best.pose, best.score, best.source),)
    t = time.perf_counter()
    for _ in range(3):  # a better turn may itself have better turns
        window = _window(search, best.pose) * (2 if search.full is search.exact else 3)
        modes = explore_modes(search.full, best.pose, object_model,
                              coarse_likelihood=search.small, maxiter=params.refine_maxiter,
                              num_refine=int(params.mode_refine),
                              ring_margin=window if params.ring_modes else None)
        top = modes[0]
        if not top.log_likelihood > best.score + 1e-6:
            break
        log.info("a near-symmetric turn (%s) beats the search's winner by %.1f nats",
                 top.origin, top.log_likelihood - best.score)
        best = Hypothesis(top.T_scene_object, float(top.log_likelihood), top.origin)
    # Modes a few nats outside the window may be inside it once polished (step 7) or on the
    # whole object (when the search ran on a subsample).
    window = _window(search, best.pose) * (2 if search.full is search.exact else 3)
    kept = tuple(m for m in modes if m.log_likelihood >= top.log_likelihood - window)
    search.timings["modes"] = time.perf_counter() - t
    return best, kept


#: Whether :func:`estimate_mle` polishes its winner (step 7) while the certifier finishes, before
#: waiting for it (the same result as after it; False: after, the reference order).
FINISH_BESIDE_CERTIFIER = True


def _certificate(search: _Search, certifier: _Certifier, best: Hypothesis,
                 modes: tuple[PoseMode, ...], finals: list[Hypothesis], eq2_result: Any,
                 eq2_ll: float, gen: np.random.Generator) -> tuple[Any, ...]:
    """Step 4: the certificate, waited for only now (it ran beside the whole search); a better
    eq. (2) pose from the certifier is one more hypothesis (appended to ``finals``), which hops
    when it beats the winner and is a candidate mode when near it.

    Step 7 (:func:`_finish`, the winner's polish) runs first, beside the certifier's last
    moments, and is kept when the certifier returns the minimiser it was given (the case of
    every pair of ``examples/benchmarks/bench_mle.py``: it saves the wait of a certificate begun
    late, about a turn that won); otherwise the polish is undone (its evaluations and time
    uncounted) and done after the new hypothesis, as without it. Returns ``best``, ``modes``,
    the finished ``(best, modes)`` or None, the certified result and eq. (1) at its pose."""
    from certpose.estimation.batch import refine_poses
    from certpose.estimation.modes import PoseMode

    timings = search.timings
    n_eval, before = search.n_eval, dict(timings)
    finished: tuple[Hypothesis, tuple[PoseMode, ...]] | None = (
        _finish(search, best, modes) if FINISH_BESIDE_CERTIFIER else None)
    t = time.perf_counter()
    certified = certifier.result()
    wait = time.perf_counter() - t
    if not np.allclose(certified.T_target_source, eq2_result.T_target_source, atol=1e-9):
        if finished is not None:
            search.n_eval, finished = n_eval, None
            timings.clear()
            timings.update(before)
        t = time.perf_counter()
        eq2_ll = float(search.exact(certified.T_target_source))
        T2, v2 = refine_poses(search.counted(search.full), certified.T_target_source[None],
                              scale=search.scale, max_iter=search.params.refine_maxiter)
        h = Hypothesis(T2[0], float(v2[0]), "eq2")
        finals.append(h)
        if h.score > best.score:
            h = _hop(search, [h], gen)
            if h.score > best.score:
                best = h
        if h.score >= best.score - 3 * _window(search, best.pose):
            modes = (*modes, PoseMode(h.pose, h.score, h.source))
        timings["eq2_certified_pose"] = time.perf_counter() - t
    timings["eq2_certify_wait"] = wait
    timings["eq2_certify"] = float(certified.info.get("certify_time", 0.0))
    return best, modes, finished, certified, eq2_ll


#: Positive voxels per object-model point below which :func:`estimate_mle` warns that the pose
#: rests on little evidence. Measured with the mask classifier on the 60 shared YCB-Video pairs
#: (geometry-only models): 0.136-0.351 (the tomato soup can least); best buddies inside
#: box.txt's boxes: 0.137 (the mug, 0000/000001) and 0.23-0.25 (the potted meat can on 0049 with
#: a model from 0002's views). A 5 x 5 pixel box on 0000/000001 gave 2 positives for the mug's
#: 2288 points (0.0009) and a pose 43 cm off. Below it the search still runs and returns its
#: pose, with the status :attr:`MLEStatus.LITTLE_EVIDENCE` (not a success) and a warning.
LITTLE_EVIDENCE = 0.02


#: Metres: a positive voxel within this of a posed model point is explained by the pose.
EXPLAIN_DISTANCE = 0.015

#: Least share of the positive voxels a pose must explain to be reported as converged, by
#: classifier (``ObjectClassification.method``). A mask marks the object alone: true poses on
#: the 60 shared YCB-Video pairs explain 77-100% of its positives, and the mustard bottle or the
#: banana moved 8-13 cm off 0-48%. Best buddies inside a box also mark the object's look-alikes
#: there, and true poses explain as little as 10% of them (the wood block in 0002/000001, the
#: banana in 0002 34-44%): the test does not separate them from wrong ones, and is not applied.
EXPLAINED = {"mask": 0.5, "best_buddies": 0.0}


def explained_fraction(classification: ObjectClassification, object_model: ObjectModel,
                       T_scene_object: ArrayLike, grid: Any, *,
                       distance: float = EXPLAIN_DISTANCE) -> float:
    """Share of the classifier's positive voxels that lie within ``distance`` metres of the
    object model's points posed by ``T_scene_object`` (4, 4); 1 without positives. ``grid``: the
    scene's :class:`~certpose.model.grid.GridSpec`.

    A pose that explains under :data:`EXPLAINED` (its classifier's share) of them is reported as
    :attr:`MLEStatus.UNEXPLAINED`: the evidence it was asked to explain lies elsewhere (a box
    whose positives belong to another object as much as to this one, a pose that slid off).
    """
    from scipy.spatial import cKDTree

    idx = np.argwhere(classification.positive)
    if idx.shape[0] == 0:
        return 1.0
    centres = grid.centres(idx)
    T = np.asarray(T_scene_object, dtype=np.float64)
    posed = object_model.points @ T[:3, :3].T + T[:3, 3]
    d = cKDTree(posed).query(centres, distance_upper_bound=distance)[0]
    return float(np.mean(d <= distance))


def _little_evidence(classification: ObjectClassification, object_model: ObjectModel) -> str | None:
    """The message (also logged as a warning) when the pose would rest on little evidence."""
    n_pos = int(np.count_nonzero(classification.positive))
    n_model = len(object_model)
    if n_pos >= LITTLE_EVIDENCE * n_model:
        return None
    msg = (f"only {n_pos} occupied voxel(s) classified as the object for a model of {n_model} "
           f"points ({n_pos / max(n_model, 1):.4f} per point, under {LITTLE_EVIDENCE:g}; real "
           "frames give 0.13-0.35): the pose rests on little evidence")
    log.warning("%s", msg)
    return msg


def estimate_mle(
    scene: Any,
    classification: ObjectClassification,
    object_model: ObjectModel,
    *,
    params: MLEParams | None = None,
    likelihood_params: LikelihoodParams | None = None,
    viewpoint: ArrayLike | None = None,
    rng: np.random.Generator | int | None = None,
) -> MLEResult:
    """Maximum-likelihood pose of ``object_model`` in ``scene`` (see the module docstring).

    Parameters
    ----------
    scene : SceneField
    classification : ObjectClassification
    object_model : ObjectModel
    params : MLEParams, optional
    likelihood_params : LikelihoodParams, optional
    viewpoint : (3,) array_like, optional
        Camera centre in the scene frame (orients the coarse search's depth offsets).
    rng : numpy Generator, int or None

    Returns
    -------
    MLEResult
        ``success`` is False (with the identity pose) when the classifier found no object voxel.
    """
    from certpose.model.grid import scene_grid_spec
    from certpose.model.likelihood import LikelihoodParams

    params = params or MLEParams()
    lparams = likelihood_params or LikelihoodParams()
    gen = resolve_rng(rng)
    t_start = time.perf_counter()
    if not classification.success:
        return MLEResult(np.eye(4), float("nan"), "none", None, float("nan"), float("nan"), None,
                         0, {}, MLEStatus.NO_OBJECT_EVIDENCE, classification.message)
    little = _little_evidence(classification, object_model)

    search = _build_likelihoods(scene, classification, object_model, params, lparams, gen)
    timings = search.timings
    grid = scene_grid_spec(scene)
    centres = evidence_centres(classification.positive, grid,
                               radius=object_model.radius, max_centres=params.num_centres)
    positives = grid.centres(np.argwhere(classification.positive))
    centre = centres[0]

    def view_from(c: NDArray[np.float64]) -> NDArray[np.float64] | None:
        return None if viewpoint is None else c - np.asarray(viewpoint, dtype=np.float64).reshape(3)

    view = view_from(centre)
    eq2_refined_ll = float("nan")
    with _Certifier() as certifier:
        coarse = _coarse_hypotheses(search, centre, view, gen, positives)
        seeded, eq2, eq2_result, hyps = _eq2_hypotheses(search, scene, classification,
                                                        object_model, lparams, gen, certifier,
                                                        coarse)
        finals = _refine_hypotheses(search, hyps)
        certified_from = None
        if seeded is not None:
            eq2, eq2_result, certified_from = _certify_seeded(search, seeded, finals, certifier)
        eq2_ll = float("nan")
        if eq2_result is not None:
            search.n_eval += 1
            eq2_ll = float(search.exact(eq2_result.T_target_source))
        # Every point in unobserved space scores N log p_unobserved: a plateau that a failed
        # search ends on (measured: the mustard bottle in 0050/000020, ADD-S 9 cm). Search again.
        # Search again from the other centres of the classifier's evidence, then from the
        # first one with new rotations.
        hidden = search.full.total_weight * lparams.log_p_unobserved + 1.0
        for attempt, c in enumerate([*centres[1:], centre, centre][:2]):
            if max((h.score for h in finals), default=-math.inf) > hidden:
                break
            log.warning("the search ended with the object hidden in unobserved space; "
                        "searching again (%d)", attempt + 1)
            finals += _refine_hypotheses(search, _coarse_hypotheses(search, c, view_from(c), gen,
                                                                positives))
        if not finals:  # no hypothesis at all (eq. (2) failed and the coarse search is disabled)
            T0 = np.eye(4)
            T0[:3, 3] = centre - object_model.centroid
            T2, v2 = search.refine(search.full, T0, maxiter=params.refine_maxiter)
            finals.append(Hypothesis(T2, v2, "centroid"))
        best = _hop(search, finals, gen)
        early = None
        if certified_from is not None and best.source != certified_from:
            # Another hypothesis hopped past the minimiser certified: eq. (2) again about the
            # winner now, so that its certificate runs beside the turns (step 6), which leave
            # the winner as it is unless a turn wins (then once more about the turn, below).
            t = time.perf_counter()
            eq2, eq2_result, certified_from = _certify_seeded(search, seeded, finals, certifier,
                                                              about=best)
            early = best
            timings["eq2_about_winner"] = time.perf_counter() - t
        best, modes = _modes(search, best, object_model)
        if best.source.startswith("turn:"):
            best = _hop(search, [best], gen)
        if early is not None and best is early:
            search.n_eval += 1
            eq2_ll = float(search.exact(eq2_result.T_target_source))
        elif certified_from is not None and best.source != certified_from:
            # The winner is in another basin than the minimiser certified (a near-symmetric
            # turn, or another hypothesis that hopped past it): eq. (2) again about the winner,
            # so that the certified minimiser is the returned pose's (measured: the mustard
            # bottle box only in 0002/000010 and 000020, raw ADD-S 1.12 and 1.29 cm, the turn).
            t = time.perf_counter()
            eq2, eq2_result, certified_from = _certify_seeded(search, seeded, finals, certifier,
                                                              about=best)
            search.n_eval += 1
            eq2_ll = float(search.exact(eq2_result.T_target_source))
            timings["eq2_about_winner"] = (timings.get("eq2_about_winner", 0.0)
                                           + time.perf_counter() - t)
        finished = None
        if certifier.running:
            best, modes, finished, eq2_result, eq2_ll = _certificate(
                search, certifier, best, modes, finals, eq2_result, eq2_ll, gen)
    best, modes = finished if finished is not None else _finish(search, best, modes)
    # The hypotheses as they ended on the search's eq. (1), scored on the exact one.
    if search.full is not search.exact and finals:
        scores = np.atleast_1d(search.counted(search.exact)(np.stack([h.pose for h in finals])))
        finals = [Hypothesis(h.pose, float(v), h.source) for h, v in zip(finals, scores, strict=True)]
    eq2_refined_ll = max((h.score for h in finals if _is_eq2(h)), default=float("nan"))
    if _is_eq2(best):
        eq2_refined_ll = best.score
    timings["total"] = time.perf_counter() - t_start
    cert = None if eq2_result is None else eq2_result.certificate
    msg = (f"best of {len(finals)} refined hypotheses on eq. (1): {best.source}; "
           f"eq. (2) pose scores {eq2_ll:.1f} ({eq2_refined_ll:.1f} refined) vs {best.score:.1f}")
    if len(modes) > 1:
        msg += (f"; {len(modes)} modes within {params.mode_window:g} tempered nats (rotations "
                + ", ".join(f"{m.rotation_from_best_deg:.0f}" for m in modes[1:])
                + " deg from the best)")
    log.info("MLE: %s", msg)
    status = MLEStatus.CONVERGED
    explained = explained_fraction(classification, object_model, best.pose, grid)
    msg += f"; the pose explains {100 * explained:.0f}% of the positive voxels"
    if little is not None:
        status, msg = MLEStatus.LITTLE_EVIDENCE, f"{little}; {msg}"
    elif explained < EXPLAINED.get(classification.method, 0.5):
        status = MLEStatus.UNEXPLAINED
        least = EXPLAINED.get(classification.method, 0.5)
        msg = (f"the pose explains only {100 * explained:.0f}% of the classifier's positive voxels "
               f"(within {100 * EXPLAIN_DISTANCE:g} cm; under {100 * least:.0f}%): the evidence "
               f"lies elsewhere, do not trust it; {msg}")
        log.warning("%s", msg.split("; ")[0])
    return MLEResult(best.pose, float(best.score), best.source, eq2_result, eq2_ll,
                     eq2_refined_ll, cert, int(search.n_eval), timings, status, msg,
                     tuple(finals), modes, eq2)


def global_search(
    likelihood: PoseLikelihood,
    centre: ArrayLike,
    *,
    radius: float,
    budget: int = 20_000,
    batch: int = 64,
    optimizer: str = "TwoPointsDE",
    rng: np.random.Generator | int | None = None,
) -> tuple[NDArray[np.float64], float]:
    """Long global search of eq. (1) with Nevergrad (the paper's appendix uses TwoPointsDE).

    The search space: the object's centroid in a cube of half-side ``radius`` around
    ``centre`` (metres) and its rotation vector in ``[-pi, pi]^3``. Candidates are asked in
    batches of ``batch`` and evaluated together.

    Parameters
    ----------
    likelihood : PoseLikelihood
    centre : (3,) array_like
        Centre of the translation box, scene frame, metres.
    radius : float
        Half-side of the translation box, metres.
    budget : int
        Eq. (1) evaluations.
    batch : int
        Candidates per ask/evaluate/tell round.
    optimizer : str
        A Nevergrad optimizer name.
    rng : numpy Generator, int or None
        Seeds Nevergrad's parametrization.

    Returns
    -------
    T : (4, 4) ndarray
        The best pose found.
    value : float
        Its eq. (1).
    """
    import nevergrad as ng

    from solvers.lie import make_transform, so3_exp

    gen = resolve_rng(rng)
    c = np.asarray(centre, dtype=np.float64).reshape(3)
    param = ng.p.Array(shape=(6,), lower=-1.0, upper=1.0)
    param.random_state = np.random.RandomState(int(gen.integers(2**31 - 1)))
    opt = ng.optimizers.registry[optimizer](parametrization=param, budget=int(budget),
                                            num_workers=int(batch))

    def to_pose(x: NDArray[np.float64]) -> NDArray[np.float64]:
        R = so3_exp(np.pi * x[3:])
        return make_transform(R, c + radius * x[:3] - R @ likelihood.centroid)

    best_T, best_v = np.eye(4), -np.inf
    done = 0
    while done < budget:
        cands = [opt.ask() for _ in range(min(batch, budget - done))]
        poses = np.stack([to_pose(np.asarray(cd.value)) for cd in cands])
        values = np.asarray(likelihood(poses))
        for cd, v in zip(cands, values, strict=True):
            opt.tell(cd, -float(v))
        i = int(np.argmax(values))
        if values[i] > best_v:
            best_v, best_T = float(values[i]), poses[i]
        done += len(cands)
    return best_T, best_v
