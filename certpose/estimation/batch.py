r"""Many local refinements of eq. (1) at once: one batched likelihood call per iteration.

:func:`~certpose.estimation.mle.refine_pose` runs scipy's BFGS on one pose; its Python overhead
(not eq. (1), which evaluates ~10^6 point terms per millisecond) is what limits how many
hypotheses can be refined. :func:`refine_poses` moves all hypotheses together: each
iteration evaluates, for every hypothesis still moving, a trial step along its normalised
central-difference gradient together with the 12 difference points around the trial, in one
call of the batched eq. (1). A trial that improves is kept and the step grows; one that does
not is dropped and the step shrinks (a per-hypothesis trust region). The objective is
piecewise linear (trilinear interpolation), which suits a normalised-gradient method with
step control better than curvature models.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from certpose.model.likelihood import PoseLikelihood

__all__ = ["refine_poses", "twists_to_poses"]

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
    from scipy.spatial.transform import Rotation

    H, M = X.shape[:2]
    D = np.zeros((H * M, 4, 4))
    flat = X.reshape(-1, 6)
    D[:, :3, :3] = Rotation.from_rotvec(flat[:, 3:]).as_matrix()
    D[:, :3, 3] = flat[:, :3] * scale
    D[:, 3, 3] = 1.0
    return np.einsum("hij,hmjk->hmik", T0, D.reshape(H, M, 4, 4))


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
        Iterations (batched likelihood calls after the first).
    step : float
        Initial trust-region step in chart units.
    min_step : float
        A hypothesis stops when its step falls below this.
    max_step : float
        Upper bound of the step.
    fd_step : float
        Central-difference step in chart units (also smooths the piecewise-linear objective).

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
    H = T.shape[0]
    if H == 0:
        return T, np.zeros(0)
    stencil = np.vstack([np.zeros(6), fd_step * np.eye(6), -fd_step * np.eye(6)])  # (13, 6)

    def evaluate(base: NDArray[np.float64], offsets: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        X = offsets[:, None, :] + stencil[None]  # (h, 13, 6)
        v = np.asarray(likelihood(twists_to_poses(base, X, scale).reshape(-1, 4, 4)))
        v = v.reshape(-1, 13)
        return v[:, 0], (v[:, 1:7] - v[:, 7:]) / (2.0 * fd_step)

    value, grad = evaluate(T, np.zeros((H, 6)))
    radius = np.full(H, float(step))
    active = np.ones(H, dtype=bool)
    for _ in range(int(max_iter)):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        g = grad[idx]
        norm = np.linalg.norm(g, axis=1)
        flat = norm <= 1e-12
        d = np.divide(g, norm[:, None], out=np.zeros_like(g), where=~flat[:, None])
        trial = d * radius[idx, None]
        v_new, g_new = evaluate(T[idx], trial)
        better = v_new > value[idx]
        if better.any():
            ib = idx[better]
            T[ib] = twists_to_poses(T[ib], trial[better][:, None, :], scale)[:, 0]
            value[ib] = v_new[better]
            grad[ib] = g_new[better]
            radius[ib] = np.minimum(radius[ib] * 1.6, max_step)
        worse = idx[~better]
        radius[worse] *= 0.4
        active[idx[flat]] = False
        active[radius < min_step] = False
    return T, value
