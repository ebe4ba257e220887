"""Closed-form weighted Procrustes (Horn/Umeyama) with determinant correction.

The one implementation of the weighted rigid least-squares fit: :func:`procrustes_kernel` is
compiled by numba (imported on first use, not with :mod:`solvers`) and serves both the public
:func:`weighted_procrustes` and the GNC-TLS kernel of :mod:`solvers.registration`, which calls
it in every iteration. :func:`weighted_rotation` is its rotation step on a given 3x3 matrix (also
the projection onto SO(3), :func:`solvers.lie.project_to_so3`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["weighted_procrustes", "weighted_rotation", "procrustes_kernel"]


def weighted_rotation(H: ArrayLike) -> NDArray[np.float64]:
    """Rotation ``R`` maximising ``tr(R^T H)``, i.e. ``argmin sum w ||b - R a||^2``.

    ``H = sum_k w_k b_k a_k^T`` (3, 3); the SVD solution is corrected so that ``det R = +1``.
    """
    U, _, Vt = np.linalg.svd(np.asarray(H, dtype=np.float64))
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        U = U.copy()
        U[:, 2] = -U[:, 2]
    return U @ Vt


def _procrustes(a, b, w):  # pragma: no cover - compiled by procrustes_kernel
    """Weighted Horn/Umeyama on (N, 3) arrays; returns (R, t, ok), ``ok`` False for sum(w) <= 0.

    Written for numba (explicit loops, no temporaries of size N); rows of zero weight are skipped.
    The rotation step is :func:`weighted_rotation`'s, spelled out because numba cannot call a
    Python function.
    """
    n = a.shape[0]
    sw = 0.0
    ca = np.zeros(3)
    cb = np.zeros(3)
    for k in range(n):
        sw += w[k]
        for d in range(3):
            ca[d] += w[k] * a[k, d]
            cb[d] += w[k] * b[k, d]
    if not sw > 0.0:
        return np.eye(3), np.zeros(3), False
    ca /= sw
    cb /= sw
    H = np.zeros((3, 3))
    for k in range(n):
        if w[k] == 0.0:
            continue
        for i in range(3):
            bi = w[k] * (b[k, i] - cb[i])
            for j in range(3):
                H[i, j] += bi * (a[k, j] - ca[j])
    U, _, Vt = np.linalg.svd(H)
    # 3x3 determinants and products spelled out: numba's np.linalg.det and matmul would add
    # about a second to the first run's compilation.
    det_u = (U[0, 0] * (U[1, 1] * U[2, 2] - U[1, 2] * U[2, 1])
             - U[0, 1] * (U[1, 0] * U[2, 2] - U[1, 2] * U[2, 0])
             + U[0, 2] * (U[1, 0] * U[2, 1] - U[1, 1] * U[2, 0]))
    det_v = (Vt[0, 0] * (Vt[1, 1] * Vt[2, 2] - Vt[1, 2] * Vt[2, 1])
             - Vt[0, 1] * (Vt[1, 0] * Vt[2, 2] - Vt[1, 2] * Vt[2, 0])
             + Vt[0, 2] * (Vt[1, 0] * Vt[2, 1] - Vt[1, 1] * Vt[2, 0]))
    if det_u * det_v < 0.0:
        for i in range(3):
            U[i, 2] = -U[i, 2]
    R = np.zeros((3, 3))
    t = cb.copy()
    for i in range(3):
        for j in range(3):
            for k in range(3):
                R[i, j] += U[i, k] * Vt[k, j]
        for j in range(3):
            t[i] -= R[i, j] * ca[j]
    return R, t, True


@functools.cache
def procrustes_kernel() -> Callable[..., Any]:
    """The compiled weighted Procrustes ``(a, b, w) -> (R, t, ok)`` (numba, cached on disk).

    Takes C-contiguous float64 arrays ``a``, ``b`` (N, 3) and ``w`` (N,); callable from other
    numba kernels.
    """
    from numba import njit

    return njit(cache=True)(_procrustes)


def weighted_procrustes(
    source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Weighted least-squares rigid alignment ``argmin_{R,t} sum_k w_k ||b_k - R a_k - t||^2``.

    Parameters
    ----------
    source, target : (N, 3) array_like
        Corresponding points ``a_k`` and ``b_k``.
    weights : (N,) array_like or None
        Non-negative weights with a positive sum; default all ones.

    Returns
    -------
    R : (3, 3) ndarray
    t : (3,) ndarray
        The pose mapping ``source`` onto ``target``.
    """
    # Fresh writable C arrays: one compiled signature whatever the caller passes.
    a = np.array(source, dtype=np.float64, order="C")
    b = np.array(target, dtype=np.float64, order="C")
    if a.ndim != 2 or a.shape[1:] != (3,) or b.shape != a.shape:
        raise ValueError(f"Expected `source` and `target` to have the same shape (N, 3), got "
                         f"{a.shape} and {b.shape}.")
    w = (np.ones(a.shape[0]) if weights is None
         else np.array(weights, dtype=np.float64, order="C").reshape(-1))
    if w.shape != (a.shape[0],):
        raise ValueError(f"Expected `weights` to have shape ({a.shape[0]},), got {w.shape}.")
    R, t, ok = procrustes_kernel()(a, b, w)
    if not ok:
        raise ValueError("`weights` must have a positive sum.")
    return R, t
