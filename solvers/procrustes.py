"""Closed-form weighted Procrustes (Horn/Umeyama) with determinant correction."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["weighted_procrustes", "weighted_rotation"]


def weighted_rotation(H: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation ``R`` maximising ``tr(R^T H)``... i.e. ``argmin sum w ||b - R a||^2``.

    ``H = sum_k w_k b_k a_k^T`` (3, 3); the SVD solution is corrected so that ``det R = +1``.
    """
    U, _, Vt = np.linalg.svd(H)
    d = np.linalg.det(U) * np.linalg.det(Vt)
    if d < 0:
        U = U.copy()
        U[:, 2] = -U[:, 2]
    return U @ Vt


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
    a = np.asarray(source, dtype=np.float64)
    b = np.asarray(target, dtype=np.float64)
    w = np.ones(a.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    sw = w.sum()
    if not sw > 0:
        raise ValueError("`weights` must have a positive sum.")
    ca = w @ a / sw
    cb = w @ b / sw
    H = ((b - cb) * w[:, None]).T @ (a - ca)
    R = weighted_rotation(H)
    return R, cb - R @ ca
