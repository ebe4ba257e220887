"""Weighted Procrustes (Horn/Umeyama): the rigid least-squares fit, always a proper rotation.

The one implementation of the weighted rigid least-squares fit is the numba kernel of
:mod:`solvers._linalg_kernels` (imported on first use, not with :mod:`solvers`); through
:func:`procrustes_kernel` it serves both the public
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


@functools.cache
def procrustes_kernel() -> Callable[..., Any]:
    """The compiled weighted Procrustes ``(a, b, w) -> (R, t, ok)`` (numba, cached on disk).

    Takes C-contiguous float64 arrays ``a``, ``b`` (N, 3) and ``w`` (N,); callable from other
    numba kernels.
    """
    from solvers.jit import compiled

    return compiled("solvers._linalg_kernels").procrustes


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
