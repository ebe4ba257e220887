"""Numba kernel of the per-pixel free-space test; imported lazily by :mod:`certpose.model.freespace`.

For each pose and object point: transform the point into every view's camera, project it to the
nearest pixel and compare its depth ``z`` with that pixel's (min-filtered) measured depth ``d``.
The point's free-space fraction is ``clip((d - z - tolerance) / ramp, 0, 1)`` (a step at
``tolerance`` when ``ramp`` is 0), 0 where the pixel has no depth (``d == 0``), outside the image or
behind the camera. Each view holds ``L`` depth images (min-filtered over growing windows), stored
pixel by pixel (``depth[view, row, column, level]``: one cache line serves all of a pixel's levels,
where an image after image layout read ``L`` lines scattered megabytes apart): a view's fraction is
their mean, and the largest fraction over the views counts.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numba import types as nt

from solvers.jit import kernel

F1, F2, F3 = nt.float64[::1], nt.float64[:, ::1], nt.float64[:, :, ::1]
F4 = nt.float64[:, :, :, ::1]
I1 = nt.int64[::1]
f8 = nt.float64
# After the poses and points: depth (V, H, W, L) per view, pixel and level, camera-from-world
# (V, 4, 4), intrinsics (V, 4) = fx, fy, cx, cy, widths (V,), heights (V,), tolerance, ramp.
_VIEWS = (F4, F3, F2, I1, I1, f8, f8)

# Poses per block of free_batch (as in certpose.model._kernels: the poses of a batch are often
# close, so a point's pixels are read from memory once and reused from cache by the block).
_POSE_BLOCK = 32


@njit(inline="always")
def _fraction(qx, qy, qz, depth, T_cw, K, widths, heights, tol, ramp):  # pragma: no cover
    levels = depth.shape[3]
    best = 0.0
    for f in range(T_cw.shape[0]):
        z = T_cw[f, 2, 0] * qx + T_cw[f, 2, 1] * qy + T_cw[f, 2, 2] * qz + T_cw[f, 2, 3]
        if z <= 1e-9:
            continue
        x = T_cw[f, 0, 0] * qx + T_cw[f, 0, 1] * qy + T_cw[f, 0, 2] * qz + T_cw[f, 0, 3]
        y = T_cw[f, 1, 0] * qx + T_cw[f, 1, 1] * qy + T_cw[f, 1, 2] * qz + T_cw[f, 1, 3]
        u = np.floor(K[f, 0] * x / z + K[f, 2] + 0.5)
        v = np.floor(K[f, 1] * y / z + K[f, 3] + 0.5)
        if u < 0.0 or v < 0.0 or u >= widths[f] or v >= heights[f]:
            continue
        frac = 0.0
        iv = int(v)
        iu = int(u)
        for lv in range(levels):
            d = depth[f, iv, iu, lv]
            if d <= 0.0:
                break
            gap = d - z - tol
            if ramp > 0.0:
                frac += min(max(gap / ramp, 0.0), 1.0)
            elif gap > 0.0:
                frac += 1.0
        frac /= levels
        if frac > best:
            best = frac
    return best


@kernel(F3, F2, F1, *_VIEWS, nogil=True)
def free_batch(T, points, weights, depth, T_cw, K, widths, heights, tol, ramp):  # pragma: no cover
    """Weighted sum of the points' free-space fractions for each of the ``B`` poses ``T`` (B, 4, 4).

    Points are the outer loop within blocks of ``_POSE_BLOCK`` poses; each pose's fractions are
    still summed in point order, so the values are those of a pose-by-pose loop."""
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
            wi = weights[i]
            for j in range(nb):
                qx = R[j, 0] * px + R[j, 1] * py + R[j, 2] * pz + R[j, 3]
                qy = R[j, 4] * px + R[j, 5] * py + R[j, 6] * pz + R[j, 7]
                qz = R[j, 8] * px + R[j, 9] * py + R[j, 10] * pz + R[j, 11]
                frac = _fraction(qx, qy, qz, depth, T_cw, K, widths, heights, tol, ramp)
                if frac > 0.0:
                    out[b0 + j] += wi * frac
    return out


@kernel(F2, F2, *_VIEWS, nogil=True)
def free_points(T, points, depth, T_cw, K, widths, heights, tol, ramp):  # pragma: no cover
    """Free-space fraction of each point ``(N,)`` at one pose ``T`` (4, 4)."""
    out = np.empty(points.shape[0])
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        qx = T[0, 0] * px + T[0, 1] * py + T[0, 2] * pz + T[0, 3]
        qy = T[1, 0] * px + T[1, 1] * py + T[1, 2] * pz + T[1, 3]
        qz = T[2, 0] * px + T[2, 1] * py + T[2, 2] * pz + T[2, 3]
        out[i] = _fraction(qx, qy, qz, depth, T_cw, K, widths, heights, tol, ramp)
    return out
