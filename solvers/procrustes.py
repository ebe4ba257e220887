"""Weighted Procrustes (Horn/Umeyama): the rigid least-squares fit, always a proper rotation.

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
    The rotation step solves :func:`weighted_rotation`'s problem by Horn's unit quaternion (the
    top eigenvector of a symmetric 4x4 matrix, always a proper rotation), found by cyclic Jacobi
    rotations: the same optimum as the corrected SVD, without LAPACK's SVD, whose numba
    specialisations cost about a second of compilation on a first run.
    """
    n = a.shape[0]
    # One allocation form (np.empty with a shape tuple): each distinct numpy constructor
    # signature is a separate compilation on the first run.
    R = np.empty((3, 3))
    t = np.empty(3)
    sw = 0.0
    ca0 = ca1 = ca2 = 0.0
    cb0 = cb1 = cb2 = 0.0
    for k in range(n):
        wk = w[k]
        sw += wk
        ca0 += wk * a[k, 0]
        ca1 += wk * a[k, 1]
        ca2 += wk * a[k, 2]
        cb0 += wk * b[k, 0]
        cb1 += wk * b[k, 1]
        cb2 += wk * b[k, 2]
    if not sw > 0.0:
        for i in range(3):
            t[i] = 0.0
            for j in range(3):
                R[i, j] = 1.0 if i == j else 0.0
        return R, t, False
    ca0 /= sw
    ca1 /= sw
    ca2 /= sw
    cb0 /= sw
    cb1 /= sw
    cb2 /= sw
    h00 = h01 = h02 = h10 = h11 = h12 = h20 = h21 = h22 = 0.0
    for k in range(n):
        wk = w[k]
        if wk == 0.0:
            continue
        x0 = a[k, 0] - ca0
        x1 = a[k, 1] - ca1
        x2 = a[k, 2] - ca2
        y0 = wk * (b[k, 0] - cb0)
        y1 = wk * (b[k, 1] - cb1)
        y2 = wk * (b[k, 2] - cb2)
        h00 += y0 * x0
        h01 += y0 * x1
        h02 += y0 * x2
        h10 += y1 * x0
        h11 += y1 * x1
        h12 += y1 * x2
        h20 += y2 * x0
        h21 += y2 * x1
        h22 += y2 * x2
    # Horn's quaternion: the eigenvector of the largest eigenvalue of the symmetric 4x4 K,
    # by cyclic Jacobi rotations (scalar code: LAPACK's SVD costs a second of compilation).
    sxx, sxy, sxz = h00, h10, h20
    syx, syy, syz = h01, h11, h21
    szx, szy, szz = h02, h12, h22
    K = np.empty((4, 4))
    K[0, 0] = sxx + syy + szz
    K[0, 1] = K[1, 0] = syz - szy
    K[0, 2] = K[2, 0] = szx - sxz
    K[0, 3] = K[3, 0] = sxy - syx
    K[1, 1] = sxx - syy - szz
    K[1, 2] = K[2, 1] = sxy + syx
    K[1, 3] = K[3, 1] = szx + sxz
    K[2, 2] = -sxx + syy - szz
    K[2, 3] = K[3, 2] = syz + szy
    K[3, 3] = -sxx - syy + szz
    V = np.empty((4, 4))
    for i in range(4):
        for j in range(4):
            V[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(50):
        off = 0.0
        scale = 0.0
        for i in range(4):
            scale += K[i, i] * K[i, i]
            for j in range(i + 1, 4):
                off += K[i, j] * K[i, j]
        if off <= 1e-36 * scale or off == 0.0:
            break
        for p in range(3):
            for q in range(p + 1, 4):
                apq = K[p, q]
                if apq == 0.0:
                    continue
                theta = (K[q, q] - K[p, p]) / (2.0 * apq)
                tt = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(tt * tt + 1.0)
                sn = tt * c
                for k in range(4):
                    kp = K[k, p]
                    kq = K[k, q]
                    K[k, p] = c * kp - sn * kq
                    K[k, q] = sn * kp + c * kq
                for k in range(4):
                    pk = K[p, k]
                    qk = K[q, k]
                    K[p, k] = c * pk - sn * qk
                    K[q, k] = sn * pk + c * qk
                for k in range(4):
                    vp = V[k, p]
                    vq = V[k, q]
                    V[k, p] = c * vp - sn * vq
                    V[k, q] = sn * vp + c * vq
    m = 0
    for i in range(1, 4):
        if K[i, i] > K[m, m]:
            m = i
    q0, q1, q2, q3 = V[0, m], V[1, m], V[2, m], V[3, m]
    qn = np.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    q0 /= qn
    q1 /= qn
    q2 /= qn
    q3 /= qn
    R[0, 0] = q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3
    R[0, 1] = 2.0 * (q1 * q2 - q0 * q3)
    R[0, 2] = 2.0 * (q1 * q3 + q0 * q2)
    R[1, 0] = 2.0 * (q1 * q2 + q0 * q3)
    R[1, 1] = q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3
    R[1, 2] = 2.0 * (q2 * q3 - q0 * q1)
    R[2, 0] = 2.0 * (q1 * q3 - q0 * q2)
    R[2, 1] = 2.0 * (q2 * q3 + q0 * q1)
    R[2, 2] = q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3
    t[0] = cb0 - (R[0, 0] * ca0 + R[0, 1] * ca1 + R[0, 2] * ca2)
    t[1] = cb1 - (R[1, 0] * ca0 + R[1, 1] * ca1 + R[1, 2] * ca2)
    t[2] = cb2 - (R[2, 0] * ca0 + R[2, 1] * ca1 + R[2, 2] * ca2)
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
