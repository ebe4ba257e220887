r"""Many local refinements of eq. (1) at once: one batched likelihood call per iteration.

:func:`~certpose.estimation.mle.refine_pose` runs scipy's BFGS on one pose; its Python overhead
(not eq. (1), which evaluates ~10^6 point terms per millisecond) is what limits how many
hypotheses can be refined. :func:`refine_poses` moves all hypotheses together: each
iteration evaluates, for every hypothesis still moving, a trial step along its normalised
central-difference gradient (one call of the batched eq. (1)), then the 12 difference points
around the trials that improved (a second call). A trial that improves is kept and the step
grows; one that does not is dropped and the step shrinks (a per-hypothesis trust region). The objective is
piecewise linear (trilinear interpolation), which suits a normalised-gradient method with
step control better than curvature models.

:func:`basin_hop` does not stop at the first local maximum: it perturbs the best pose at random,
refines the perturbed poses (first on a cheap eq. (1), then the best few on the exact one, all
batched) and keeps any that climbs higher, for a few rounds. scipy's ``basinhopping`` does the
same one start at a time; batching is what makes it affordable here.

:func:`polish_poses` is the last, derivative-free step at the top of a basin (where the
difference gradient stalls on the piecewise-linear objective): a compass search, the 12 poses
one step along each chart axis evaluated in one call per iteration, the best improving one
taken, the step halved when none improves. scipy's Powell does the same job one evaluation at
a time, with ~1 ms of Python per evaluation against ~0.15 ms of eq. (1).
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from certpose.model.likelihood import PoseLikelihood

__all__ = ["basin_hop", "polish_poses", "refine_poses", "twists_to_poses"]

log = logging.getLogger(__name__)


def twists_to_poses(T0: NDArray[np.float64], X: NDArray[np.float64], scale: float) -> NDArray[np.float64]:
    """``T0[h] @ [exp(omega), scale * rho]`` for rows ``[rho, omega]`` of ``X`` (H, M, 6).

    Parameters
    ----------
    T0 : (H, 4, 4) ndarray
    X : (H, M, 6) ndarray
    scale : float
        Metres per unit of ``rho``.

    Returns
    -------
    (H, M, 4, 4) ndarray
    """
    from solvers.lie import so3_exp_batch

    H, M = X.shape[:2]
    D = np.zeros((H * M, 4, 4))
    flat = X.reshape(-1, 6)
    D[:, :3, :3] = so3_exp_batch(flat[:, 3:])  # scipy's numbers, without its call overhead
    D[:, :3, 3] = flat[:, :3] * scale
    D[:, 3, 3] = 1.0
    return np.matmul(T0[:, None], D.reshape(H, M, 4, 4))  # 2-4x faster than einsum here


def refine_poses(
    likelihood: PoseLikelihood,
    T0: ArrayLike,
    *,
    scale: float,
    max_iter: int = 40,
    step: float = 0.05,
    min_step: float = 2e-3,
    max_step: float = 0.5,
    fd_step: float = 0.02,
    prune_margin: float | None = None,
    prune_every: int = 10,
    merge: float | None = None,
    groups: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Locally maximise eq. (1) from each of ``T0`` (see the module docstring).

    Parameters
    ----------
    likelihood : PoseLikelihood
    T0 : (H, 4, 4) array_like
        Starting ``T_scene_object`` poses.
    scale : float
        Metres per unit of translation in the local chart (e.g. the object radius); one unit
        of rotation is one radian.
    max_iter : int
        Iterations (up to two batched likelihood calls each: the trials, then the gradients
        where they improved).
    step : float
        Initial trust-region step in chart units.
    min_step : float
        A hypothesis stops when its step falls below this.
    max_step : float
        Upper bound of the step.
    fd_step : float
        Central-difference step in chart units (also smooths the piecewise-linear objective).
    prune_margin : float, optional
        For callers that keep only the best hypothesis and those near it (see
        :func:`~certpose.estimation.modes.explore_modes`): every ``prune_every`` iterations, a
        hypothesis stops where it is when, climbing on at its rate of the last 5 iterations
        for every iteration left, it would still end more than ``prune_margin`` nats below
        the best hypothesis now. A hypothesis far behind but climbing fast goes on (measured:
        a turn of the potted-meat can, 0002/000020, climbed from 220 nats behind to the top
        in 30 iterations). ``None``: no pruning.
    prune_every : int
        Iterations between the pruning checks.
    merge : float, optional
        For callers that keep only the best hypothesis of each group (see :func:`basin_hop`):
        after every iteration, a hypothesis within ``merge`` chart units (``sqrt(|dt|^2 /
        scale^2 + angle^2)``, angle in radians) of a better one of its group stops where it
        is: two climbs onto one pose are done once. ``None``: no merging.
    groups : (H,) array_like of int, optional
        Group of each hypothesis for ``merge`` (default: one group).

    Returns
    -------
    T : (H, 4, 4) ndarray
        Refined poses (never worse than the starts).
    values : (H,) ndarray
        Eq. (1) at ``T``.
    """
    T = np.array(T0, dtype=np.float64)
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"Expected `T0` to have shape (H, 4, 4), got {T.shape}.")
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"`scale` must be positive, got {scale}.")
    if prune_margin is not None and not prune_margin >= 0:
        raise ValueError(f"`prune_margin` must be >= 0 nats or None, got {prune_margin}.")
    if int(prune_every) < 5:
        raise ValueError(f"`prune_every` must be >= 5 iterations, got {prune_every}.")
    if merge is not None and not (math.isfinite(merge) and merge >= 0):
        raise ValueError(f"`merge` must be >= 0 chart units or None, got {merge}.")
    H = T.shape[0]
    grp = np.zeros(H, dtype=np.int64) if groups is None else np.asarray(groups, dtype=np.int64)
    if grp.shape != (H,):
        raise ValueError(f"Expected `groups` to have shape ({H},), got {grp.shape}.")
    if H == 0:
        return T, np.zeros(0)
    # Values at the 12 central-difference points around a chart offset (the trial itself
    # is evaluated first, alone).
    stencil = np.vstack([fd_step * np.eye(6), -fd_step * np.eye(6)])  # (12, 6)

    def gradient(base: NDArray[np.float64], offsets: NDArray[np.float64]) -> NDArray[np.float64]:
        X = offsets[:, None, :] + stencil[None]  # (h, 12, 6)
        v = np.asarray(likelihood(twists_to_poses(base, X, scale).reshape(-1, 4, 4))).reshape(-1, 12)
        return (v[:, :6] - v[:, 6:]) / (2.0 * fd_step)

    value = np.asarray(likelihood(T), dtype=np.float64).reshape(H)
    grad = gradient(T, np.zeros((H, 6)))
    radius = np.full(H, float(step))
    active = np.ones(H, dtype=bool)
    past: list[NDArray[np.float64]] = []  # values after each iteration (for the pruning)
    for it in range(int(max_iter)):
        if prune_margin is not None:
            past.append(value.copy())
            if it > 0 and it % int(prune_every) == 0:
                rate = np.maximum(value - past[it - 5], 0.0) / 5.0
                active &= value + (int(max_iter) - it) * rate >= value.max() - prune_margin
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        g = grad[idx]
        norm = np.linalg.norm(g, axis=1)
        flat = norm <= 1e-12
        d = np.divide(g, norm[:, None], out=np.zeros_like(g), where=~flat[:, None])
        trial = d * radius[idx, None]
        # The trial alone first: the gradient is needed only where the trial is kept (about
        # half the trials fail near a maximum, and each would cost 12 evaluations more). The
        # stencil stays in the chart of the old pose, so the path is the one of evaluating
        # the 13 points together.
        v_new = np.asarray(likelihood(twists_to_poses(T[idx], trial[:, None, :], scale)[:, 0]),
                           dtype=np.float64).reshape(-1)
        better = v_new > value[idx]
        if better.any():
            ib = idx[better]
            grad[ib] = gradient(T[ib], trial[better])
            T[ib] = twists_to_poses(T[ib], trial[better][:, None, :], scale)[:, 0]
            value[ib] = v_new[better]
            radius[ib] = np.minimum(radius[ib] * 1.6, max_step)
        worse = idx[~better]
        radius[worse] *= 0.4
        active[idx[flat]] = False
        active[radius < min_step] = False
        if merge is not None and active.any():
            active &= ~_merged(T, value, grp, scale, float(merge))
    return T, value


def _merged(T: NDArray[np.float64], value: NDArray[np.float64], grp: NDArray[np.int64],
            scale: float, tol: float) -> NDArray[np.bool_]:
    """Which poses lie within ``tol`` chart units of a better pose of their group (ties: of
    an earlier one)."""
    dt = np.linalg.norm(T[:, None, :3, 3] - T[None, :, :3, 3], axis=-1) / scale
    cos = (np.einsum("aij,bij->ab", T[:, :3, :3], T[:, :3, :3]) - 1.0) / 2.0
    near = dt**2 + np.arccos(np.clip(cos, -1.0, 1.0)) ** 2 <= tol**2
    i = np.arange(T.shape[0])
    better = (value[None, :] > value[:, None]) | ((value[None, :] == value[:, None])
                                                  & (i[None, :] < i[:, None]))
    return np.any(near & better & (grp[None, :] == grp[:, None]), axis=1)


def _check_starts(T0: ArrayLike, scale: float) -> NDArray[np.float64]:
    """``T0`` as a float64 (H, 4, 4) copy, with the checks of :func:`basin_hop` and
    :func:`polish_poses`."""
    T = np.array(T0, dtype=np.float64)
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"Expected `T0` to have shape (4, 4) or (H, 4, 4) and finite values, "
                         f"got {T.shape}.")
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"`scale` must be positive, got {scale}.")
    return T


def basin_hop(
    likelihood: PoseLikelihood,
    T0: ArrayLike,
    *,
    scale: float,
    coarse_likelihood: PoseLikelihood | None = None,
    rounds: int = 3,
    samples: int = 32,
    keep: int = 4,
    translation: float = 0.08,
    rotation_deg: float = 8.0,
    max_iter: int = 30,
    coarse_max_iter: int = 15,
    drop_behind: float = math.inf,
    merge: float | None = 0.02,
    rng: np.random.Generator | int | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Climb from each of ``T0`` past the local maxima next to it (see the module docstring).

    Each round draws, for every start, ``samples`` poses ``T @ [exp(omega), scale * rho]``
    around its best pose ``T`` so far, with ``rho ~ N(0, translation^2)`` and
    ``omega ~ N(0, rotation_deg^2)`` per axis; refines them on ``coarse_likelihood``
    (``coarse_max_iter`` iterations), keeps the ``keep`` best on ``likelihood`` and refines those
    on it (``max_iter``). A refined pose that beats ``T`` replaces it. All starts share one
    batched eq. (1) call per iteration.

    Parameters
    ----------
    likelihood : PoseLikelihood
        The exact eq. (1).
    T0 : (4, 4) or (H, 4, 4) array_like
        Starting ``T_scene_object`` poses (usually local maxima already).
    scale : float
        Metres per unit of ``rho`` (e.g. the object radius).
    coarse_likelihood : PoseLikelihood, optional
        A cheaper eq. (1) for the first refinement (e.g. an object subsample); without it every
        sample is refined on ``likelihood``.
    rounds, samples, keep : int
        Rounds of perturbation, poses drawn per start and round, poses per start refined on
        ``likelihood`` per round.
    translation : float
        Standard deviation of each translation coordinate, in units of ``scale``.
    rotation_deg : float
        Standard deviation of each rotation-vector coordinate, degrees.
    max_iter, coarse_max_iter : int
        Iterations of :func:`refine_poses` on ``likelihood`` and ``coarse_likelihood``.
    drop_behind : float
        After each round, a start whose best pose trails the best start's by more than this
        many nats stops hopping (its best so far is returned). The perturbations are drawn
        for every start all the same, so the starts that go on follow the same path as
        without the cut.
    merge : float or None
        ``merge`` of both refinements, per start (only each start's best is kept): a pose
        that comes within this many chart units of a better one of its start stops, and of
        the ``keep`` best after the cheap refinement, those within it of a better one are not
        refined again. Measured on the hop's exact refinements of 15 YCB-Video pairs
        (``examples/benchmarks/bench_basins.py``): 56% ended within 0.02 units and 2 degrees of a better
        one of their start; with 0.02 (the central-difference step: their gradients come from
        overlapping stencils) the hop evaluated 16% fewer point terms on 20 of those pairs, every
        pair within 0.2 nats of its value without. ``None``: every pose climbs to the end.
    rng : numpy Generator, int or None

    Returns
    -------
    T : (H, 4, 4) ndarray
        The best pose found from each start (the start when nothing beat it).
    values : (H,) ndarray
        Eq. (1) at ``T`` (on ``likelihood``).
    """
    from solvers.validation import resolve_rng

    T = _check_starts(T0, scale)
    if int(samples) < 1 or int(keep) < 1 or int(rounds) < 0:
        raise ValueError(f"`samples` and `keep` must be >= 1 and `rounds` >= 0, got {samples}, "
                         f"{keep} and {rounds}.")
    if not (translation >= 0 and rotation_deg >= 0):
        raise ValueError(f"`translation` and `rotation_deg` must be >= 0, got {translation} and "
                         f"{rotation_deg}.")
    if not drop_behind >= 0:
        raise ValueError(f"`drop_behind` must be >= 0 nats, got {drop_behind}.")
    gen = resolve_rng(rng)
    H, M = T.shape[0], int(samples)
    values = np.asarray(likelihood(T), dtype=np.float64).reshape(H)
    live = np.arange(H)
    for _ in range(int(rounds)):
        X = np.empty((H, M, 6))
        X[..., :3] = gen.normal(scale=translation, size=(H, M, 3))
        X[..., 3:] = gen.normal(scale=math.radians(rotation_deg), size=(H, M, 3))
        h = live.size
        P = twists_to_poses(T[live], X[live], scale).reshape(-1, 4, 4)
        rows = np.arange(h)[:, None]
        keep_mask = np.ones((h, M), dtype=bool)
        if coarse_likelihood is not None:
            groups = np.repeat(np.arange(h), M)
            P, _ = refine_poses(coarse_likelihood, P, scale=scale, max_iter=coarse_max_iter,
                                merge=merge, groups=groups)
            k = min(int(keep), M)
            exact = np.asarray(likelihood(P), dtype=np.float64).reshape(h, M)
            # Of the best, those that climbed onto a better one's pose are not refined again.
            dup = (np.zeros((h, M), dtype=bool) if merge is None
                   else _merged(P, exact.ravel(), groups, scale, float(merge)).reshape(h, M))
            top = np.argsort(-exact, axis=1)[:, :k]
            P = P.reshape(h, M, 4, 4)[rows, top]
            keep_mask = ~dup[rows, top]
        else:
            P = P.reshape(h, M, 4, 4)
        v = np.full(keep_mask.shape, -np.inf)
        P[keep_mask], v[keep_mask] = refine_poses(
            likelihood, P[keep_mask], scale=scale, max_iter=max_iter, merge=merge,
            groups=np.broadcast_to(rows, keep_mask.shape)[keep_mask])
        i = np.argmax(v, axis=1)
        better = v[np.arange(h), i] > values[live]
        T[live[better]] = P[better, i[better]]
        values[live[better]] = v[better, i[better]]
        live = live[values[live] >= values.max() - drop_behind]
    return T, values


def polish_poses(
    likelihood: PoseLikelihood,
    T0: ArrayLike,
    *,
    scale: float,
    step: float = 0.02,
    min_step: float = 1e-3,
    max_iter: int = 200,
    axes: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], int]:
    """Compass search of eq. (1) from each of ``T0`` (see the module docstring).

    Parameters
    ----------
    likelihood : PoseLikelihood
    T0 : (4, 4) or (H, 4, 4) array_like
        Starting ``T_scene_object`` poses (local maxima of a coarser refinement, usually).
    scale : float
        Metres per unit of the chart's translation coordinates (e.g. the object radius).
    step : float
        First step along each chart axis (translation in units of ``scale``, rotation in radians).
    min_step : float
        A pose stops when its step falls below this.
    max_iter : int
        Iteration limit (one batched eq. (1) call each).
    axes : (k, 6) array_like, optional
        The chart directions searched (default: the 12 of ``+-`` each axis); e.g. a subset to
        climb with some coordinates held.

    Returns
    -------
    T : (H, 4, 4) ndarray
    values : (H,) ndarray
        Eq. (1) at ``T``; never below its value at ``T0``.
    evaluations : int
        Poses scored.
    """
    T = _check_starts(T0, scale)
    if not (step > 0 and 0 < min_step <= step):
        raise ValueError(f"Expected 0 < `min_step` <= `step`, got {min_step} and {step}.")
    H = T.shape[0]
    values = np.asarray(likelihood(T), dtype=np.float64).reshape(H)
    n_eval = H
    steps = np.full(H, float(step))
    if axes is None:
        axes = np.vstack([np.eye(6), -np.eye(6)])
    else:
        axes = np.asarray(axes, dtype=np.float64)
        if axes.ndim != 2 or axes.shape[1] != 6 or axes.shape[0] == 0 or not np.all(np.isfinite(axes)):
            raise ValueError(f"Expected `axes` to have shape (k, 6) with k >= 1 and finite entries, got {np.shape(axes)}.")
    k = axes.shape[0]
    for _ in range(int(max_iter)):
        live = np.flatnonzero(steps >= min_step)
        if live.size == 0:
            break
        X = steps[live, None, None] * axes[None]
        P = twists_to_poses(T[live], X, scale)
        v = np.asarray(likelihood(P.reshape(-1, 4, 4)), dtype=np.float64).reshape(live.size, k)
        n_eval += v.size
        j = np.argmax(v, axis=1)
        best = v[np.arange(live.size), j]
        up = best > values[live]
        T[live[up]] = P[np.flatnonzero(up), j[up]]
        values[live[up]] = best[up]
        steps[live[~up]] *= 0.5
    return T, values, n_eval
