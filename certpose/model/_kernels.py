"""Numba kernels of eq. (1); imported lazily by :mod:`certpose.model.likelihood`.

Grid encoding shared with the Python side: ``index[x, y, z] >= 0`` is the row of an occupied
voxel in the compact arrays; at every other voxel (observed free space, ``EMPTY_CODE``, or
unobserved space, ``UNOBSERVED_CODE``) the per-voxel value is ``background[x, y, z]`` (the
free-space penalty, possibly graded by the distance to the observed surface, or the unobserved
prior; unobserved voxels always hold ``c_unobs``). ``cells[x, y, z]`` tells when the 8 voxel
centres around a cell share one value and no occupied corner, so the kernel returns it without
interpolating: ``UNIFORM_EMPTY`` (all ``c_empty``) and ``UNIFORM_UNOBSERVED`` (all unobserved)
without reading ``background`` (the common cells, kept free of a second memory access),
``UNIFORM`` (another shared value, e.g. graded free space) from it. Points outside the (padded)
grid count as unobserved.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numba import types as nt

from solvers.jit import kernel

# Argument types of the declared signatures: C-contiguous, writable arrays.
F1, F2, F3 = nt.float64[::1], nt.float64[:, ::1], nt.float64[:, :, ::1]
S2, I3, B3 = nt.float32[:, ::1], nt.int32[:, :, ::1], nt.int8[:, :, ::1]
f4, f8 = nt.float32, nt.float64
# Everything after the pose: points, their weights, descriptors, grid index, cell states,
# background values, voxel descriptors, log p_O, origin, 1 / voxel size, offset, beta, c_empty,
# c_unobs.
_MODEL = (F2, F1, S2, I3, B3, F3, S2, F1, F1, f8, f8, f4, f8, f8)

EMPTY_CODE = -1
UNOBSERVED_CODE = -2
MIXED, UNIFORM_EMPTY, UNIFORM_UNOBSERVED, UNIFORM = 0, 1, 2, 3


@njit(inline="always")
def _point_term(index, cells, background, desc, logp, zi, qx, qy, qz, origin, inv_vs, offset, beta,
                c_empty, c_unobs):  # pragma: no cover
    # Continuous coordinates in the padded grid (one unobserved voxel on each side), integer
    # values at voxel centres.
    ux = (qx - origin[0]) * inv_vs - offset + 1.0
    uy = (qy - origin[1]) * inv_vs - offset + 1.0
    uz = (qz - origin[2]) * inv_vs - offset + 1.0
    fx0 = np.floor(ux)
    fy0 = np.floor(uy)
    fz0 = np.floor(uz)
    nx, ny, nz = cells.shape
    if fx0 < 0.0 or fy0 < 0.0 or fz0 < 0.0 or fx0 >= nx or fy0 >= ny or fz0 >= nz:
        return c_unobs
    x0 = int(fx0)
    y0 = int(fy0)
    z0 = int(fz0)
    # Cells whose 8 corners share one non-occupied value need no interpolation.
    cell = cells[x0, y0, z0]
    if cell == UNIFORM_EMPTY:
        return c_empty
    if cell == UNIFORM_UNOBSERVED:
        return c_unobs
    if cell == UNIFORM:
        return background[x0, y0, z0]
    ax = ux - fx0
    ay = uy - fy0
    az = uz - fz0
    acc = 0.0
    for dx in range(2):
        wx = ax if dx == 1 else 1.0 - ax
        for dy in range(2):
            wxy = wx * (ay if dy == 1 else 1.0 - ay)
            for dz in range(2):
                w = wxy * (az if dz == 1 else 1.0 - az)
                v = index[x0 + dx, y0 + dy, z0 + dz]
                if v >= 0:
                    s = np.float32(0.0)
                    for k in range(zi.shape[0]):
                        s += desc[v, k] * zi[k]
                    acc += w * (logp[v] + beta * s)
                elif v == EMPTY_CODE:
                    acc += w * background[x0 + dx, y0 + dy, z0 + dz]
                else:
                    acc += w * c_unobs
    return acc


# Poses per block of eq1_batch (their 12 transform entries stay in L1 beside the point).
_POSE_BLOCK = 32


@kernel(F3, *_MODEL, fastmath=True, nogil=True)
def eq1_batch(T, points, weights, zdesc, index, cells, background, desc, logp, origin, inv_vs, offset, beta,
              c_empty, c_unobs):  # pragma: no cover - compiled
    """Weighted sum of per-point log-localisation terms for each of the ``B`` poses ``T`` (B, 4, 4).

    The one eq. (1) kernel. It releases the GIL, so :mod:`certpose.model.likelihood` runs
    large batches as chunks on a thread pool: no ``parallel=True`` second copy to compile.
    Points are the outer loop within blocks of ``_POSE_BLOCK`` poses: the poses of a batch are
    often close (a refinement's 12 finite-difference poses), so a point's descriptor and the
    voxels it lands on are read once from memory and reused from cache by the whole block
    (measured: about 20% less time per term on such batches). Each pose's terms are still
    summed in point order, so the values are the same as pose by pose.
    """
    B = T.shape[0]
    out = np.zeros(B)
    R = np.empty((_POSE_BLOCK, 12))
    for b0 in range(0, B, _POSE_BLOCK):
        nb = min(_POSE_BLOCK, B - b0)
        for j in range(nb):
            for r in range(3):
                for c in range(4):
                    R[j, 4 * r + c] = T[b0 + j, r, c]
        for i in range(points.shape[0]):
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            zi = zdesc[i]
            wi = weights[i]
            for j in range(nb):
                qx = R[j, 0] * px + R[j, 1] * py + R[j, 2] * pz + R[j, 3]
                qy = R[j, 4] * px + R[j, 5] * py + R[j, 6] * pz + R[j, 7]
                qz = R[j, 8] * px + R[j, 9] * py + R[j, 10] * pz + R[j, 11]
                out[b0 + j] += wi * _point_term(index, cells, background, desc, logp, zi, qx, qy, qz, origin,
                                                inv_vs, offset, beta, c_empty, c_unobs)
    return out


@kernel(F2, *_MODEL, fastmath=True, nogil=True)
def eq1_points(T, points, weights, zdesc, index, cells, background, desc, logp, origin, inv_vs, offset, beta,
               c_empty, c_unobs):  # pragma: no cover - compiled
    """Per-point weighted terms ``(N,)`` for one pose ``T`` (4, 4)."""
    N = points.shape[0]
    out = np.empty(N)
    for i in range(N):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        qx = T[0, 0] * px + T[0, 1] * py + T[0, 2] * pz + T[0, 3]
        qy = T[1, 0] * px + T[1, 1] * py + T[1, 2] * pz + T[1, 3]
        qz = T[2, 0] * px + T[2, 1] * py + T[2, 2] * pz + T[2, 3]
        out[i] = weights[i] * _point_term(index, cells, background, desc, logp, zdesc[i], qx, qy, qz, origin, inv_vs,
                             offset, beta, c_empty, c_unobs)
    return out
