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

``eq1_batch_graded`` and ``eq1_points_graded`` charge free space at the point instead
(``LikelihoodParams.free_space_at="point"``): EMPTY voxels hold ``c_unobs`` (plus any blurred
classifier term) in ``background`` and their distance into free space in ``depth`` (metres, 0
elsewhere); the distances of a mixed cell's corners are blended like the values, and a point whose
blend exceeds ``fs_start`` pays the fraction ``min(1, (blend - fs_start) / fs_ramp)`` of
``c_empty - c_unobs`` on top (a step when ``fs_ramp`` is 0). ``UNIFORM`` cells are then cells
without any charge and ``UNIFORM_EMPTY`` cells fully charged ones
(:func:`certpose.model.likelihood._cell_codes`). Separate kernels, so that the default one keeps
its arguments and speed.
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
# The graded kernels' further arguments: distance into free space (metres), where the charge
# starts and its ramp (metres).
_GRADED = (F3, f8, f8)

EMPTY_CODE = -1
UNOBSERVED_CODE = -2
MIXED, UNIFORM_EMPTY, UNIFORM_UNOBSERVED, UNIFORM = 0, 1, 2, 3


@njit(inline="always")
def _cell(cells, qx, qy, qz, origin, inv_vs, offset):  # pragma: no cover
    """The padded grid's cell of a scene point: its lowest corner (-1 when outside the grid),
    its state code and the point's offsets in it (0..1 per axis)."""
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
        return -1, 0, 0, UNIFORM_UNOBSERVED, 0.0, 0.0, 0.0
    x0 = int(fx0)
    y0 = int(fy0)
    z0 = int(fz0)
    return x0, y0, z0, cells[x0, y0, z0], ux - fx0, uy - fy0, uz - fz0


@njit(inline="always")
def _corner_values(index, background, desc, logp, zi, x0, y0, z0, beta, c_unobs,
                   cv):  # pragma: no cover
    """The 8 values of a mixed cell's corners for one point (descriptor ``zi``) into ``cv``."""
    k = 0
    for dx in range(2):
        for dy in range(2):
            for dz in range(2):
                v = index[x0 + dx, y0 + dy, z0 + dz]
                if v >= 0:
                    s = np.float32(0.0)
                    for m in range(zi.shape[0]):
                        s += desc[v, m] * zi[m]
                    cv[k] = logp[v] + beta * s
                elif v == EMPTY_CODE:
                    cv[k] = background[x0 + dx, y0 + dy, z0 + dz]
                else:
                    cv[k] = c_unobs
                k += 1


@njit(inline="always")
def _interpolate(cv, ax, ay, az):  # pragma: no cover
    acc = 0.0
    k = 0
    for dx in range(2):
        wx = ax if dx == 1 else 1.0 - ax
        for dy in range(2):
            wxy = wx * (ay if dy == 1 else 1.0 - ay)
            for dz in range(2):
                acc += wxy * (az if dz == 1 else 1.0 - az) * cv[k]
                k += 1
    return acc


@njit(inline="always")
def _cache_row(keys, x0, y0, z0):  # pragma: no cover
    """The row of the batch kernels' corner-value cache (8, 8) for the cell ``(x0, y0, z0)`` of
    one point, and whether it holds that cell's values already (``keys`` (8, 3): the cell of
    each row, ``-1`` when empty; updated to this cell). A cell goes to the row of its
    coordinates' parities, so the 8 cells around a voxel centre, between which the poses of a
    batch send a point back and forth, never evict each other."""
    e = (x0 & 1) + 2 * (y0 & 1) + 4 * (z0 & 1)
    if keys[e, 0] == x0 and keys[e, 1] == y0 and keys[e, 2] == z0:
        return e, True
    keys[e, 0] = x0
    keys[e, 1] = y0
    keys[e, 2] = z0
    return e, False


@njit(inline="always")
def _uniform_value(background, x0, y0, z0, cell, c_empty, c_unobs):  # pragma: no cover
    """The value of a cell whose 8 corners share one non-occupied value (no interpolation)."""
    if cell == UNIFORM_EMPTY:
        return c_empty
    if cell == UNIFORM_UNOBSERVED:
        return c_unobs
    return background[x0, y0, z0]


@njit(inline="always")
def _point_term(T, points, i, zdesc, index, cells, background, desc, logp, origin, inv_vs, offset,
                beta, c_empty, c_unobs, cv):  # pragma: no cover
    """Point ``i``'s unweighted term of eq. (1) at the pose ``T`` (4, 4) (``cv``: scratch (8,))."""
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    qx = T[0, 0] * px + T[0, 1] * py + T[0, 2] * pz + T[0, 3]
    qy = T[1, 0] * px + T[1, 1] * py + T[1, 2] * pz + T[1, 3]
    qz = T[2, 0] * px + T[2, 1] * py + T[2, 2] * pz + T[2, 3]
    x0, y0, z0, cell, ax, ay, az = _cell(cells, qx, qy, qz, origin, inv_vs, offset)
    if x0 < 0:
        return c_unobs
    if cell != MIXED:
        return _uniform_value(background, x0, y0, z0, cell, c_empty, c_unobs)
    _corner_values(index, background, desc, logp, zdesc[i], x0, y0, z0, beta, c_unobs, cv)
    return _interpolate(cv, ax, ay, az)


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
    summed in point order, so the values are the same as pose by pose. A point's 8 corner
    values depend on its cell only: they are kept for the block's later poses that put the
    point in that cell again (about a millimetre apart, a 5 mm voxel), which skips their
    look-ups and descriptor products (measured, one thread, CPU time: 43 -> 26 ns per term on
    batches of finite-difference poses near the truth, and 207 -> 127 ms on 2048 random
    rotations, the kernel's simpler branches; values within 1e-12 nats of the kernel before,
    whose fastmath sums ran in another order). Up to 8 cells are kept per point, one per parity
    of the cell's coordinates (:func:`_cache_row`): a finite-difference stencil sends a point
    back and forth between neighbouring cells, which a single kept cell lost each time
    (measured on the recorded batches of three YCB-Video pairs' MLE: corner values
    recomputed for 28-41% of the terms in mixed cells instead of 48-67%; 5-15% less time per
    term in this kernel and :func:`eq1_batch_visible`, the same values bit for bit).
    """
    B = T.shape[0]
    out = np.zeros(B)
    R = np.empty((_POSE_BLOCK, 12))
    cache = np.empty((8, 8))  # corner values of up to 8 cells of the point (_cache_row)
    keys = np.empty((8, 3), dtype=np.int64)
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
            for e in range(8):
                keys[e, 0] = -1
            for j in range(nb):
                qx = R[j, 0] * px + R[j, 1] * py + R[j, 2] * pz + R[j, 3]
                qy = R[j, 4] * px + R[j, 5] * py + R[j, 6] * pz + R[j, 7]
                qz = R[j, 8] * px + R[j, 9] * py + R[j, 10] * pz + R[j, 11]
                x0, y0, z0, cell, ax, ay, az = _cell(cells, qx, qy, qz, origin, inv_vs, offset)
                if x0 < 0:
                    out[b0 + j] += wi * c_unobs
                    continue
                if cell != MIXED:
                    out[b0 + j] += wi * _uniform_value(background, x0, y0, z0, cell, c_empty,
                                                       c_unobs)
                    continue
                e, held = _cache_row(keys, x0, y0, z0)
                cv = cache[e]
                if not held:
                    _corner_values(index, background, desc, logp, zi, x0, y0, z0, beta, c_unobs, cv)
                out[b0 + j] += wi * _interpolate(cv, ax, ay, az)
    return out


@kernel(F2, *_MODEL, fastmath=True, nogil=True)
def eq1_points(T, points, weights, zdesc, index, cells, background, desc, logp, origin, inv_vs, offset, beta,
               c_empty, c_unobs):  # pragma: no cover - compiled
    """Per-point weighted terms ``(N,)`` for one pose ``T`` (4, 4)."""
    N = points.shape[0]
    out = np.empty(N)
    cv = np.empty(8)
    for i in range(N):
        out[i] = weights[i] * _point_term(T, points, i, zdesc, index, cells, background, desc, logp,
                                          origin, inv_vs, offset, beta, c_empty, c_unobs, cv)
    return out


@njit(inline="always")
def _corner_depths(depth, x0, y0, z0, cd):  # pragma: no cover
    """The 8 distances into free space of a cell's corners into ``cd`` (order of _corner_values)."""
    k = 0
    for dx in range(2):
        for dy in range(2):
            for dz in range(2):
                cd[k] = depth[x0 + dx, y0 + dy, z0 + dz]
                k += 1


@njit(inline="always")
def _charge(g, fs_start, fs_ramp, c_empty, c_unobs):  # pragma: no cover
    """Free-space charge of a point whose blended distance into free space is ``g``."""
    if g <= fs_start:
        return 0.0
    frac = 1.0
    if fs_ramp > 0.0:
        frac = min(1.0, (g - fs_start) / fs_ramp)
    return frac * (c_empty - c_unobs)


@kernel(F3, *_MODEL, *_GRADED, fastmath=True, nogil=True)
def eq1_batch_graded(T, points, weights, zdesc, index, cells, background, desc, logp, origin, inv_vs, offset,
                     beta, c_empty, c_unobs, depth, fs_start, fs_ramp):  # pragma: no cover - compiled
    """:func:`eq1_batch` with free space charged at the point (module docstring)."""
    B = T.shape[0]
    out = np.zeros(B)
    R = np.empty((_POSE_BLOCK, 12))
    cv = np.empty(8)
    cd = np.empty(8)
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
            lx = -1
            ly = -1
            lz = -1
            for j in range(nb):
                qx = R[j, 0] * px + R[j, 1] * py + R[j, 2] * pz + R[j, 3]
                qy = R[j, 4] * px + R[j, 5] * py + R[j, 6] * pz + R[j, 7]
                qz = R[j, 8] * px + R[j, 9] * py + R[j, 10] * pz + R[j, 11]
                x0, y0, z0, cell, ax, ay, az = _cell(cells, qx, qy, qz, origin, inv_vs, offset)
                if x0 < 0:
                    out[b0 + j] += wi * c_unobs
                    continue
                if cell != MIXED:
                    out[b0 + j] += wi * _uniform_value(background, x0, y0, z0, cell, c_empty,
                                                       c_unobs)
                    continue
                if x0 != lx or y0 != ly or z0 != lz:
                    _corner_values(index, background, desc, logp, zi, x0, y0, z0, beta, c_unobs, cv)
                    _corner_depths(depth, x0, y0, z0, cd)
                    lx = x0
                    ly = y0
                    lz = z0
                out[b0 + j] += wi * (_interpolate(cv, ax, ay, az)
                                     + _charge(_interpolate(cd, ax, ay, az), fs_start, fs_ramp, c_empty,
                                               c_unobs))
    return out


@kernel(F2, *_MODEL, *_GRADED, fastmath=True, nogil=True)
def eq1_points_graded(T, points, weights, zdesc, index, cells, background, desc, logp, origin, inv_vs, offset,
                      beta, c_empty, c_unobs, depth, fs_start, fs_ramp):  # pragma: no cover - compiled
    """:func:`eq1_points` with free space charged at the point (module docstring)."""
    N = points.shape[0]
    out = np.empty(N)
    cv = np.empty(8)
    cd = np.empty(8)
    for i in range(N):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        qx = T[0, 0] * px + T[0, 1] * py + T[0, 2] * pz + T[0, 3]
        qy = T[1, 0] * px + T[1, 1] * py + T[1, 2] * pz + T[1, 3]
        qz = T[2, 0] * px + T[2, 1] * py + T[2, 2] * pz + T[2, 3]
        x0, y0, z0, cell, ax, ay, az = _cell(cells, qx, qy, qz, origin, inv_vs, offset)
        if x0 < 0:
            term = c_unobs
        elif cell != MIXED:
            term = _uniform_value(background, x0, y0, z0, cell, c_empty, c_unobs)
        else:
            _corner_values(index, background, desc, logp, zdesc[i], x0, y0, z0, beta, c_unobs, cv)
            _corner_depths(depth, x0, y0, z0, cd)
            term = _interpolate(cv, ax, ay, az) + _charge(_interpolate(cd, ax, ay, az), fs_start, fs_ramp,
                                                          c_empty, c_unobs)
        out[i] = weights[i] * term
    return out


# The visibility kernels' further arguments (certpose.model.visibility): the points' unit
# normals, the self-occlusion table (N, cells; no columns for a convex surface), cells per cube
# face side, the camera centres (K, 3) in the scene frame and the facing ramp's end.
U2 = nt.uint8[:, ::1]
_VISIBLE = (F2, U2, nt.int64, F2, f8)


@njit(inline="always")
def _occlusion(vtab, i, dx, dy, dz, faces):  # pragma: no cover
    """Bilinear blend of point ``i``'s table at the direction ``(dx, dy, dz)`` (any length)."""
    ax, ay, az = abs(dx), abs(dy), abs(dz)
    if ax >= ay and ax >= az:
        k = 0 if dx > 0 else 1
        m, u, v = ax, dy, dz
    elif ay >= az:
        k = 2 if dy > 0 else 3
        m, u, v = ay, dx, dz
    else:
        k = 4 if dz > 0 else 5
        m, u, v = az, dx, dy
    if m <= 0.0:
        return 0.0
    gx = (u / m + 1.0) * 0.5 * faces + 0.5
    gy = (v / m + 1.0) * 0.5 * faces + 0.5
    i0 = min(max(int(np.floor(gx)), 0), faces)
    j0 = min(max(int(np.floor(gy)), 0), faces)
    fx = gx - i0
    fy = gy - j0
    S = faces + 2
    b = k * S * S + i0 * S + j0
    return ((1.0 - fx) * ((1.0 - fy) * vtab[i, b] + fy * vtab[i, b + 1])
            + fx * ((1.0 - fy) * vtab[i, b + S] + fy * vtab[i, b + S + 1]))


@njit(inline="always")
def _visibility(E, j, px, py, pz, nx, ny, nz, vtab, i, faces, grazing):  # pragma: no cover
    """Largest visibility of point ``i`` over the cameras ``E[j, c]`` (object frame)."""
    best = 0.0
    for c in range(E.shape[1]):
        dx = E[j, c, 0] - px
        dy = E[j, c, 1] - py
        dz = E[j, c, 2] - pz
        if nx * dx + ny * dy + nz * dz <= 0.0:
            continue  # facing away (f <= 0 below): no square root, no division
        dn = np.sqrt(dx * dx + dy * dy + dz * dz)
        if dn <= 0.0:
            continue
        f = (nx * dx + ny * dy + nz * dz) / (dn * grazing)
        if f <= 0.0:
            continue
        if f > 1.0:
            f = 1.0
        if vtab.shape[1] > 0:
            f *= _occlusion(vtab, i, dx, dy, dz, faces)
        if f > best:
            best = f
    return best


@njit(inline="always")
def _cameras_in_object(T, cams, E, j):  # pragma: no cover
    """``E[j, c] = R^T (cams[c] - t)`` for the pose ``T`` (4, 4)."""
    for c in range(cams.shape[0]):
        rx = cams[c, 0] - T[0, 3]
        ry = cams[c, 1] - T[1, 3]
        rz = cams[c, 2] - T[2, 3]
        for a in range(3):
            E[j, c, a] = T[0, a] * rx + T[1, a] * ry + T[2, a] * rz


@kernel(F3, *_MODEL, *_VISIBLE, fastmath=True, nogil=True)
def eq1_batch_visible(T, points, weights, zdesc, index, cells, background, desc, logp, origin, inv_vs,
                      offset, beta, c_empty, c_unobs, normals, vtab, faces, cams,
                      grazing):  # pragma: no cover - compiled
    """:func:`eq1_batch` with each point's term blended by its visibility ``v`` from the cameras
    (:mod:`certpose.model.visibility`): ``v term + (1 - v) c_unobs``. A point nobody sees costs
    what unobserved space costs, whatever lies where it lands (observed free space is charged
    per pixel, outside this kernel)."""
    B = T.shape[0]
    out = np.zeros(B)
    R = np.empty((_POSE_BLOCK, 12))
    E = np.empty((_POSE_BLOCK, cams.shape[0], 3))
    cache = np.empty((8, 8))
    keys = np.empty((8, 3), dtype=np.int64)
    for b0 in range(0, B, _POSE_BLOCK):
        nb = min(_POSE_BLOCK, B - b0)
        for j in range(nb):
            for r in range(3):
                for c in range(4):
                    R[j, 4 * r + c] = T[b0 + j, r, c]
            _cameras_in_object(T[b0 + j], cams, E, j)
        for i in range(points.shape[0]):
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
            zi = zdesc[i]
            wi = weights[i]
            for e in range(8):
                keys[e, 0] = -1
            for j in range(nb):
                vis = _visibility(E, j, px, py, pz, nx, ny, nz, vtab, i, faces, grazing)
                out[b0 + j] += wi * (1.0 - vis) * c_unobs
                if vis <= 0.0:
                    continue
                qx = R[j, 0] * px + R[j, 1] * py + R[j, 2] * pz + R[j, 3]
                qy = R[j, 4] * px + R[j, 5] * py + R[j, 6] * pz + R[j, 7]
                qz = R[j, 8] * px + R[j, 9] * py + R[j, 10] * pz + R[j, 11]
                x0, y0, z0, cell, ax, ay, az = _cell(cells, qx, qy, qz, origin, inv_vs, offset)
                if x0 < 0:
                    out[b0 + j] += wi * vis * c_unobs
                    continue
                if cell != MIXED:
                    out[b0 + j] += wi * vis * _uniform_value(background, x0, y0, z0, cell, c_empty,
                                                             c_unobs)
                    continue
                e, held = _cache_row(keys, x0, y0, z0)
                cv = cache[e]
                if not held:
                    _corner_values(index, background, desc, logp, zi, x0, y0, z0, beta, c_unobs, cv)
                out[b0 + j] += wi * vis * _interpolate(cv, ax, ay, az)
    return out


@kernel(F2, *_MODEL, *_VISIBLE, fastmath=True, nogil=True)
def eq1_points_visible(T, points, weights, zdesc, index, cells, background, desc, logp, origin, inv_vs,
                       offset, beta, c_empty, c_unobs, normals, vtab, faces, cams,
                       grazing):  # pragma: no cover - compiled
    """Per-point terms ``(N,)`` of :func:`eq1_batch_visible` for one pose ``T`` (4, 4)."""
    N = points.shape[0]
    out = np.zeros(N)
    cv = np.empty(8)
    E = np.empty((1, cams.shape[0], 3))
    _cameras_in_object(T, cams, E, 0)
    for i in range(N):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        vis = _visibility(E, 0, px, py, pz, normals[i, 0], normals[i, 1], normals[i, 2], vtab, i,
                          faces, grazing)
        out[i] = weights[i] * (1.0 - vis) * c_unobs
        if vis <= 0.0:
            continue
        out[i] += weights[i] * vis * _point_term(T, points, i, zdesc, index, cells, background, desc,
                                                 logp, origin, inv_vs, offset, beta, c_empty,
                                                 c_unobs, cv)
    return out
