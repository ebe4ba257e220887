"""Small dense linear algebra compiled by numba: symmetric eigenproblems, weighted Procrustes and
rotation vectors' matrices.

Imported on first use (by :mod:`solvers.procrustes` and the registration kernels), not with
:mod:`solvers`. Written without LAPACK: numba's specialisations of LAPACK's SVD and ``eigvalsh``
(Fortran-order copies, finiteness checks, error paths) cost about a second of compilation each
on a first run, while these matrices are 3x3 and 4x4. One Jacobi routine serves both sizes, so it
compiles once.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numba import types as nt

from solvers.jit import kernel

F1, F2 = nt.float64[::1], nt.float64[:, ::1]


@njit(cache=True)
def sym_eig(A, V):  # pragma: no cover - compiled
    """Eigen-decomposition of the symmetric ``A`` (n, n) by cyclic Jacobi rotations, in place.

    On return ``A`` is diagonal (its eigenvalues, unsorted) and ``V`` holds the eigenvectors as
    columns. Accurate to a few ulps of ``||A||`` (small eigenvalues included), converges in a
    handful of sweeps for n <= 4.
    """
    n = A.shape[0]
    for i in range(n):
        for j in range(n):
            V[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(50):
        off = 0.0
        scale = 0.0
        for i in range(n):
            scale += A[i, i] * A[i, i]
            for j in range(i + 1, n):
                off += A[i, j] * A[i, j]
        if off <= 1e-36 * scale or off == 0.0:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = A[p, q]
                if apq == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                tt = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(tt * tt + 1.0)
                sn = tt * c
                for k in range(n):
                    kp = A[k, p]
                    kq = A[k, q]
                    A[k, p] = c * kp - sn * kq
                    A[k, q] = sn * kp + c * kq
                for k in range(n):
                    pk = A[p, k]
                    qk = A[q, k]
                    A[p, k] = c * pk - sn * qk
                    A[q, k] = sn * pk + c * qk
                for k in range(n):
                    vp = V[k, p]
                    vq = V[k, q]
                    V[k, p] = c * vp - sn * vq
                    V[k, q] = sn * vp + c * vq


@kernel(F2, F2, F1)
def procrustes(a, b, w):  # pragma: no cover - compiled
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
    # Horn's quaternion: the eigenvector of the largest eigenvalue of the symmetric 4x4 K.
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
    sym_eig(K, V)
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


@kernel(F2, nogil=True)
def rotvec_matrices(v):  # pragma: no cover - compiled
    """Rotation matrices (n, 3, 3) of the rotation vectors ``v`` (n, 3), radians: scipy's
    ``Rotation.from_rotvec(v).as_matrix()`` operation by operation (the unit quaternion with its
    small-angle series below 1e-3 rad, then its matrix), so the same bits, without scipy's
    per-call overhead (about 20 us, against 1.5 us here for a refinement step's 24 vectors)."""
    n = v.shape[0]
    out = np.empty((n, 3, 3))
    for i in range(n):
        v0, v1, v2 = v[i, 0], v[i, 1], v[i, 2]
        angle = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        if angle <= 1e-3:
            a2 = angle * angle
            scale = 0.5 - a2 / 48 + a2 * a2 / 3840
        else:
            scale = math.sin(angle / 2) / angle
        x, y, z, w = scale * v0, scale * v1, scale * v2, math.cos(angle / 2)
        x2, y2, z2, w2 = x * x, y * y, z * z, w * w
        xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
        out[i, 0, 0] = x2 - y2 - z2 + w2
        out[i, 1, 0] = 2 * (xy + zw)
        out[i, 2, 0] = 2 * (xz - yw)
        out[i, 0, 1] = 2 * (xy - zw)
        out[i, 1, 1] = -x2 + y2 - z2 + w2
        out[i, 2, 1] = 2 * (yz + xw)
        out[i, 0, 2] = 2 * (xz + yw)
        out[i, 1, 2] = 2 * (yz - xw)
        out[i, 2, 2] = -x2 - y2 + z2 + w2
    return out
