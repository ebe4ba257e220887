"""Numba kernels of the FPFH descriptor; imported lazily by :mod:`certpose.geometry.features`.

The same computation as open3d's ``estimate_normals`` (hybrid search, the fast 3x3 eigen
solver), ``orient_normals_towards_camera_location`` and ``compute_fpfh_feature`` (SPFH of each
point over its hybrid neighbours, then FPFH as the point's SPFH plus its neighbours' SPFH
weighted by one over their squared distance), operation by operation in the same order and
without fast-math, so the results are the same numbers (measured on YCB-Video scenes: equal
bits but for the few points whose neighbours include two at exactly the same distance, whose
order may differ: 1e-16 relative on their histograms). Being here rather than in open3d spares
a ``certpose pose`` run open3d's import (about 0.3 s of a 2 s call on this project's machine),
and the FPFH of only the points asked for (``rows``) is computed.

The kernels are ``deferred`` (:func:`solvers.jit.kernel`): they take long to compile (about
as long as all of eq. (1)'s), so while a first run's warm-up compiles them,
:class:`~certpose.geometry.features.FPFHBackbone` calls open3d instead.

Neighbours are found on a uniform grid of cell side ``cell`` (no k-d tree): those strictly
within ``radius`` (squared distance ``< radius**2``, summed as ``(dx*dx + dy*dy) + dz*dz``, as
open3d's k-d tree does), the ``max_nn`` nearest, nearest first (ties in grid order).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numba import types as nt

from solvers.jit import kernel

F1, F2, I1 = nt.float64[::1], nt.float64[:, ::1], nt.int64[::1]
f8, i8 = nt.float64, nt.int64


@njit(inline="always")
def _cross(a0, a1, a2, b0, b1, b2):  # pragma: no cover
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit
def _grid(points, cell):  # pragma: no cover
    """Points bucketed by grid cell: lowest corner, cells per axis, point order, cell starts."""
    n = points.shape[0]
    lo = np.empty(3)
    for d in range(3):
        lo[d] = points[:, d].min()
    keys = np.empty((n, 3), np.int64)
    dims = np.zeros(3, np.int64)
    for i in range(n):
        for d in range(3):
            k = int(math.floor((points[i, d] - lo[d]) / cell))
            keys[i, d] = k
            if k + 1 > dims[d]:
                dims[d] = k + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    start = np.zeros(dims[0] * dims[1] * dims[2] + 1, np.int64)
    for i in range(n):
        start[flat[i] + 1] += 1
    for c in range(start.shape[0] - 1):
        start[c + 1] += start[c]
    # A counting sort by cell (stable: points of a cell in index order); numba's argsort
    # compiles for seconds.
    order = np.empty(n, np.int64)
    fill = start[:-1].copy()
    for i in range(n):
        order[fill[flat[i]]] = i
        fill[flat[i]] += 1
    return lo, dims, order, start


@njit
def _neighbours(points, i, radius, max_nn, lo, cell, dims, order, start, idx, dist):  # pragma: no cover
    """Hybrid search around point ``i`` into ``idx`` / ``dist`` (squared); returns the count."""
    r2 = radius * radius
    reach = int(math.ceil(radius / cell))
    qx, qy, qz = points[i, 0], points[i, 1], points[i, 2]
    kx = int(math.floor((qx - lo[0]) / cell))
    ky = int(math.floor((qy - lo[1]) / cell))
    kz = int(math.floor((qz - lo[2]) / cell))
    m = 0
    for ax in range(max(kx - reach, 0), min(kx + reach + 1, dims[0])):
        for ay in range(max(ky - reach, 0), min(ky + reach + 1, dims[1])):
            for az in range(max(kz - reach, 0), min(kz + reach + 1, dims[2])):
                c = (ax * dims[1] + ay) * dims[2] + az
                for s in range(start[c], start[c + 1]):
                    j = order[s]
                    d0 = qx - points[j, 0]
                    d1 = qy - points[j, 1]
                    d2 = qz - points[j, 2]
                    dd = (d0 * d0 + d1 * d1) + d2 * d2
                    if dd < r2:
                        # Insertion into the sorted list, kept to max_nn entries (after equals).
                        p = m if m < max_nn else max_nn
                        while p > 0 and dist[p - 1] > dd:
                            if p < max_nn:
                                dist[p] = dist[p - 1]
                                idx[p] = idx[p - 1]
                            p -= 1
                        if p < max_nn:
                            dist[p] = dd
                            idx[p] = j
                        if m < max_nn:
                            m += 1
    return m


@njit
def _eigenvector0(A, e):  # pragma: no cover
    r00, r01, r02 = A[0, 0] - e, A[0, 1], A[0, 2]
    r10, r11, r12 = A[0, 1], A[1, 1] - e, A[1, 2]
    r20, r21, r22 = A[0, 2], A[1, 2], A[2, 2] - e
    a0, a1, a2 = _cross(r00, r01, r02, r10, r11, r12)
    b0, b1, b2 = _cross(r00, r01, r02, r20, r21, r22)
    c0, c1, c2 = _cross(r10, r11, r12, r20, r21, r22)
    d0 = (a0 * a0 + a1 * a1) + a2 * a2
    d1 = (b0 * b0 + b1 * b1) + b2 * b2
    d2 = (c0 * c0 + c1 * c1) + c2 * c2
    dmax, imax = d0, 0
    if d1 > dmax:
        dmax, imax = d1, 1
    if d2 > dmax:
        imax = 2
    if imax == 0:
        s = math.sqrt(d0)
        return a0 / s, a1 / s, a2 / s
    if imax == 1:
        s = math.sqrt(d1)
        return b0 / s, b1 / s, b2 / s
    s = math.sqrt(d2)
    return c0 / s, c1 / s, c2 / s


@njit
def _eigenvector1(A, e0, e1, e2, ev):  # pragma: no cover
    if abs(e0) > abs(e1):
        inv = 1 / math.sqrt(e0 * e0 + e2 * e2)
        u0, u1, u2 = -e2 * inv, 0.0, e0 * inv
    else:
        inv = 1 / math.sqrt(e1 * e1 + e2 * e2)
        u0, u1, u2 = 0.0, e2 * inv, -e1 * inv
    v0, v1, v2 = _cross(e0, e1, e2, u0, u1, u2)
    au0 = A[0, 0] * u0 + A[0, 1] * u1 + A[0, 2] * u2
    au1 = A[0, 1] * u0 + A[1, 1] * u1 + A[1, 2] * u2
    au2 = A[0, 2] * u0 + A[1, 2] * u1 + A[2, 2] * u2
    av0 = A[0, 0] * v0 + A[0, 1] * v1 + A[0, 2] * v2
    av1 = A[0, 1] * v0 + A[1, 1] * v1 + A[1, 2] * v2
    av2 = A[0, 2] * v0 + A[1, 2] * v1 + A[2, 2] * v2
    m00 = u0 * au0 + u1 * au1 + u2 * au2 - ev
    m01 = u0 * av0 + u1 * av1 + u2 * av2
    m11 = v0 * av0 + v1 * av1 + v2 * av2 - ev
    a00, a01, a11 = abs(m00), abs(m01), abs(m11)
    if a00 >= a11:
        if max(a00, a01) > 0:
            m00, m01 = _unit_pair(m00, m01, a00, a01)
            return m01 * u0 - m00 * v0, m01 * u1 - m00 * v1, m01 * u2 - m00 * v2
        return u0, u1, u2
    if max(a11, a01) > 0:
        m11, m01 = _unit_pair(m11, m01, a11, a01)
        return m11 * u0 - m01 * v0, m11 * u1 - m01 * v1, m11 * u2 - m01 * v2
    return u0, u1, u2


@njit
def _unit_pair(p, q, ap, aq):  # pragma: no cover
    """``(p, q)`` scaled to unit length, dividing by the larger of ``|p|`` (``ap``) and ``|q|``
    (``aq``) first, in Open3D's order of operations (the same bits)."""
    if ap >= aq:
        q /= p
        p = 1 / math.sqrt(1 + q * q)
        q *= p
    else:
        p /= q
        q = 1 / math.sqrt(1 + p * p)
        p *= q
    return p, q


@njit
def _smallest_of_three(A, ea, eb, ev1, x_first):  # pragma: no cover
    """The eigenvector of the smallest of the eigenvalues ``ea``, ``ev1``, ``eb`` of ``A``, in
    Open3D's order: ``ea``'s eigenvector first, then ``ev1``'s, else their cross product
    (``x_first``: ``ea``'s vector is its first factor)."""
    x0, x1, x2 = _eigenvector0(A, ea)
    if ea < eb and ea < ev1:
        return x0, x1, x2
    y0, y1, y2 = _eigenvector1(A, x0, x1, x2, ev1)
    if ev1 < ea and ev1 < eb:
        return y0, y1, y2
    if x_first:
        return _cross(x0, x1, x2, y0, y1, y2)
    return _cross(y0, y1, y2, x0, x1, x2)


@njit
def _smallest_eigenvector(C, A):  # pragma: no cover
    """Unit eigenvector of the smallest eigenvalue of the symmetric ``C`` (zero when ``C`` is):
    the closed form of Eberly's "robust eigensolver for 3x3 symmetric matrices", as open3d's
    ``fast_normal_computation``. ``A``: scratch (3, 3)."""
    mc = C[0, 0]
    for r in range(3):
        for c in range(3):
            if C[r, c] > mc:
                mc = C[r, c]
    if mc == 0:
        return 0.0, 0.0, 0.0
    for r in range(3):
        for c in range(3):
            A[r, c] = C[r, c] / mc
    norm = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
    if norm > 0:
        q = (A[0, 0] + A[1, 1] + A[2, 2]) / 3
        b00, b11, b22 = A[0, 0] - q, A[1, 1] - q, A[2, 2] - q
        p = math.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + norm * 2) / 6)
        c00 = b11 * b22 - A[1, 2] * A[1, 2]
        c01 = A[0, 1] * b22 - A[1, 2] * A[0, 2]
        c02 = A[0, 1] * A[1, 2] - b11 * A[0, 2]
        det = (b00 * c00 - A[0, 1] * c01 + A[0, 2] * c02) / (p * p * p)
        half_det = min(max(det * 0.5, -1.0), 1.0)
        angle = math.acos(half_det) / 3.0
        beta2 = math.cos(angle) * 2
        beta0 = math.cos(angle + 2.09439510239319549) * 2
        beta1 = -(beta0 + beta2)
        ev0, ev1, ev2 = q + p * beta0, q + p * beta1, q + p * beta2
        if half_det >= 0:
            return _smallest_of_three(A, ev2, ev0, ev1, False)
        return _smallest_of_three(A, ev0, ev2, ev1, True)
    if C[0, 0] < C[1, 1] and C[0, 0] < C[2, 2]:
        return 1.0, 0.0, 0.0
    if C[1, 1] < C[0, 0] and C[1, 1] < C[2, 2]:
        return 0.0, 1.0, 0.0
    return 0.0, 0.0, 1.0


@kernel(F2, f8, i8, f8, F1, nogil=True, deferred=True)
def normals_towards(points, radius, max_nn, cell, viewpoint):  # pragma: no cover - compiled
    """Unit normals (N, 3) of ``points`` (N, 3): the smallest principal axis of the covariance of
    each point's hybrid neighbours (identity covariance with fewer than 3), oriented towards
    ``viewpoint``; (0, 0, 1) where the covariance is zero, and towards the viewpoint (or
    (0, 0, 1) on it)."""
    n = points.shape[0]
    normals = np.empty((n, 3))
    if n == 0:
        return normals
    lo, dims, order, start = _grid(points, cell)
    idx = np.empty(max_nn, np.int64)
    dist = np.empty(max_nn)
    C = np.empty((3, 3))
    A = np.empty((3, 3))
    cum = np.empty(9)
    for i in range(n):
        k = _neighbours(points, i, radius, max_nn, lo, cell, dims, order, start, idx, dist)
        if k >= 3:
            cum[:] = 0.0
            for q in range(k):
                j = idx[q]
                x, y, z = points[j, 0], points[j, 1], points[j, 2]
                cum[0] += x
                cum[1] += y
                cum[2] += z
                cum[3] += x * x
                cum[4] += x * y
                cum[5] += x * z
                cum[6] += y * y
                cum[7] += y * z
                cum[8] += z * z
            for c in range(9):
                cum[c] = cum[c] / k
            C[0, 0] = cum[3] - cum[0] * cum[0]
            C[1, 1] = cum[6] - cum[1] * cum[1]
            C[2, 2] = cum[8] - cum[2] * cum[2]
            C[0, 1] = cum[4] - cum[0] * cum[1]
            C[1, 0] = C[0, 1]
            C[0, 2] = cum[5] - cum[0] * cum[2]
            C[2, 0] = C[0, 2]
            C[1, 2] = cum[7] - cum[1] * cum[2]
            C[2, 1] = C[1, 2]
        else:
            C[:, :] = 0.0
            C[0, 0] = 1.0
            C[1, 1] = 1.0
            C[2, 2] = 1.0
        a, b, c = _smallest_eigenvector(C, A)
        if math.sqrt((a * a + b * b) + c * c) == 0.0:
            a, b, c = 0.0, 0.0, 1.0
        o0 = viewpoint[0] - points[i, 0]
        o1 = viewpoint[1] - points[i, 1]
        o2 = viewpoint[2] - points[i, 2]
        if (a * o0 + b * o1) + c * o2 < 0.0:
            a, b, c = -a, -b, -c
        normals[i, 0] = a
        normals[i, 1] = b
        normals[i, 2] = c
    return normals


@njit
def _pair_bins(p1, n1, p2, n2):  # pragma: no cover
    """The three histogram bins (0..10 each) of the pair feature of (p1, n1) and (p2, n2); -1
    when the feature is zero (coincident points, or a normal along their line)."""
    dx, dy, dz = p2[0] - p1[0], p2[1] - p1[1], p2[2] - p1[2]
    nrm = math.sqrt((dx * dx + dy * dy) + dz * dz)
    if nrm == 0.0:
        return -1, -1, -1
    a0, a1, a2 = n1[0], n1[1], n1[2]
    b0, b1, b2 = n2[0], n2[1], n2[2]
    angle1 = ((a0 * dx + a1 * dy) + a2 * dz) / nrm
    angle2 = ((b0 * dx + b1 * dy) + b2 * dz) / nrm
    # acos(|angle1|) > acos(|angle2|); acos does not increase, so only |angle1| < |angle2| can
    # hold it (the acos themselves decide then: they may be equal, or NaN past 1).
    if abs(angle1) < abs(angle2) and math.acos(abs(angle1)) > math.acos(abs(angle2)):
        a0, a1, a2, b0, b1, b2 = b0, b1, b2, a0, a1, a2
        dx, dy, dz = dx * -1.0, dy * -1.0, dz * -1.0
        f2 = -angle2
    else:
        f2 = angle1
    v0, v1, v2 = _cross(dx, dy, dz, a0, a1, a2)
    vn = math.sqrt((v0 * v0 + v1 * v1) + v2 * v2)
    if vn == 0.0:
        return -1, -1, -1
    v0, v1, v2 = v0 / vn, v1 / vn, v2 / vn
    w0, w1, w2 = _cross(a0, a1, a2, v0, v1, v2)
    f1 = (v0 * b0 + v1 * b1) + v2 * b2
    f0 = math.atan2((w0 * b0 + w1 * b1) + w2 * b2, (a0 * b0 + a1 * b1) + a2 * b2)
    return (_bin(11 * (f0 + math.pi) / (2.0 * math.pi)), _bin(11 * (f1 + 1.0) * 0.5),
            _bin(11 * (f2 + 1.0) * 0.5))


@njit(inline="always")
def _bin(x):  # pragma: no cover
    h = int(math.floor(x))
    if h < 0:
        return 0
    if h >= 11:
        return 10
    return h


@kernel(F2, F2, f8, i8, f8, I1, nogil=True, deferred=True)
def fpfh(points, normals, radius, max_nn, cell, rows):  # pragma: no cover - compiled
    """FPFH histograms (len(rows), 33) of ``points[rows]`` (open3d's 0..200 scale, unnormalised)
    over all ``points`` (N, 3) with unit ``normals`` (N, 3)."""
    n = points.shape[0]
    out = np.zeros((rows.shape[0], 33))
    if n == 0:
        return out
    lo, dims, order, start = _grid(points, cell)
    slot = np.full(n, -1, np.int64)
    for r in range(rows.shape[0]):
        slot[rows[r]] = r
    spfh = np.zeros((n, 33))
    idx = np.empty(max_nn, np.int64)
    dist = np.empty(max_nn)
    nb_idx = np.empty((rows.shape[0], max_nn), np.int64)
    nb_dist = np.empty((rows.shape[0], max_nn))
    nb_k = np.zeros(rows.shape[0], np.int64)
    for i in range(n):
        k = _neighbours(points, i, radius, max_nn, lo, cell, dims, order, start, idx, dist)
        r = slot[i]
        if r >= 0:
            nb_k[r] = k
            nb_idx[r, :k] = idx[:k]
            nb_dist[r, :k] = dist[:k]
        if k > 1:
            inc = 100.0 / (k - 1)
            for q in range(1, k):  # the first is the point itself
                j = idx[q]
                h0, h1, h2 = _pair_bins(points[i], normals[i], points[j], normals[j])
                if h0 < 0:  # a zero feature counts in the bins of zero
                    h0, h1, h2 = _bin(11 * math.pi / (2.0 * math.pi)), _bin(11 * 0.5), _bin(11 * 0.5)
                spfh[i, h0] += inc
                spfh[i, h1 + 11] += inc
                spfh[i, h2 + 22] += inc
    s = np.empty(3)
    for r in range(rows.shape[0]):
        i = rows[r]
        k = nb_k[r]
        if k <= 1:
            continue
        s[:] = 0.0
        for q in range(1, k):
            d2 = nb_dist[r, q]
            if d2 == 0.0:
                continue
            j = nb_idx[r, q]
            for b in range(33):
                val = spfh[j, b] / d2
                s[b // 11] += val
                out[r, b] += val
        for b in range(3):
            if s[b] != 0.0:
                s[b] = 100.0 / s[b]
        for b in range(33):
            out[r, b] *= s[b // 11]
            out[r, b] += spfh[i, b]
    return out
