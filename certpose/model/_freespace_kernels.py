"""Numba kernel of the per-pixel free-space test; imported lazily by :mod:`certpose.model.freespace`.

For each pose and object point: transform the point into every view's camera (the pose and the
view's camera-from-world composed first), project it to the nearest pixel and compare its depth ``z`` with that pixel's (min-filtered) measured depth ``d``.
The point's free-space fraction is ``clip((d - z - tolerance) / ramp, 0, 1)`` (a step at
``tolerance`` when ``ramp`` is 0), 0 where the pixel has no depth (``d == 0``), outside the image or
behind the camera. Each view holds ``L`` depth images (min-filtered over growing windows), stored
pixel by pixel (``depth[view, row, column, level]``: one cache line serves all of a pixel's levels,
where an image after image layout read ``L`` lines scattered megabytes apart): a view's fraction is
their mean, and the largest fraction over the views counts.

Most points stand behind or on the measured surface (about 98% of the terms of the MLE's
batches on YCB-Video frames): their fraction is 0, and the kernel tells so from ``bound``, the
first level's depth rounded up to float32 (a quarter of the levels' bytes, so the look-ups
mostly hit the cache): ``bound - z - tolerance <= 0`` implies the same of every level's depth,
which is at most the first level's (the windows grow with the level, the min-filter only
lowers the depth; rounding is monotone, so the float64 test on the bound implies the one on the
depth). Likewise the levels stop at the first whose gap is not positive: the later ones add
exactly 0. The values are the same as testing every level (measured on the recorded batches of
three YCB-Video pairs' MLE: 12.5-14.7 -> 8.0-8.3 ns per term, one thread, bit for bit).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numba import types as nt

from solvers.jit import kernel

F1, F2, F3 = nt.float64[::1], nt.float64[:, ::1], nt.float64[:, :, ::1]
F4 = nt.float64[:, :, :, ::1]
S3 = nt.float32[:, :, ::1]
I1 = nt.int64[::1]
f8 = nt.float64
# After the poses and points: the first level's depth rounded up (V, H, W), depth (V, H, W, L)
# per view, pixel and level (non-increasing over the levels), camera-from-world (V, 4, 4),
# intrinsics (V, 4) = fx, fy, cx, cy, widths (V,), heights (V,), tolerance, ramp.
_VIEWS = (S3, F4, F3, F2, I1, I1, f8, f8)

# Poses per block of free_batch (as in certpose.model._kernels: the poses of a batch are often
# close, so a point's pixels are read from memory once and reused from cache by the block).
_POSE_BLOCK = 32


@njit(inline="always")
def _object_to_cameras(T, T_cw, M, j):  # pragma: no cover
    """``M[j, f]`` = the 3x4 rows of ``T_cw[f] @ T``: object points straight into view ``f``'s
    camera, one transform per point instead of two (scene, then camera)."""
    for f in range(T_cw.shape[0]):
        for r in range(3):
            for c in range(4):
                acc = T_cw[f, r, 3] if c == 3 else 0.0
                for k in range(3):
                    acc += T_cw[f, r, k] * T[k, c]
                M[j, f, 4 * r + c] = acc


@njit(inline="always")
def _fraction(px, py, pz, M, j, bound, depth, K, widths, heights, tol, ramp):  # pragma: no cover
    """Free-space fraction of the object point ``(px, py, pz)`` under the camera transforms
    ``M[j]`` (:func:`_object_to_cameras`)."""
    levels = depth.shape[3]
    best = 0.0
    for f in range(M.shape[1]):
        z = M[j, f, 8] * px + M[j, f, 9] * py + M[j, f, 10] * pz + M[j, f, 11]
        if z <= 1e-9:
            continue
        x = M[j, f, 0] * px + M[j, f, 1] * py + M[j, f, 2] * pz + M[j, f, 3]
        y = M[j, f, 4] * px + M[j, f, 5] * py + M[j, f, 6] * pz + M[j, f, 7]
        u = np.floor(K[f, 0] * x / z + K[f, 2] + 0.5)
        v = np.floor(K[f, 1] * y / z + K[f, 3] + 0.5)
        if u < 0.0 or v < 0.0 or u >= widths[f] or v >= heights[f]:
            continue
        iv = int(v)
        iu = int(u)
        if np.float64(bound[f, iv, iu]) - z - tol <= 0.0:
            continue  # every level's gap is <= 0 (module docstring)
        frac = 0.0
        for lv in range(levels):
            d = depth[f, iv, iu, lv]
            if d <= 0.0:
                break
            gap = d - z - tol
            if gap <= 0.0:
                break  # so are the later levels'
            if ramp > 0.0:
                frac += min(gap / ramp, 1.0)
            else:
                frac += 1.0
        frac /= levels
        if frac > best:
            best = frac
    return best


@kernel(F3, F2, F1, *_VIEWS, nogil=True)
def free_batch(T, points, weights, bound, depth, T_cw, K, widths, heights, tol, ramp):  # pragma: no cover
    """Weighted sum of the points' free-space fractions for each of the ``B`` poses ``T`` (B, 4, 4).

    Points are the outer loop within blocks of ``_POSE_BLOCK`` poses; each pose's fractions are
    still summed in point order, so the values are those of a pose-by-pose loop."""
    B = T.shape[0]
    out = np.zeros(B)
    M = np.empty((_POSE_BLOCK, T_cw.shape[0], 12))
    for b0 in range(0, B, _POSE_BLOCK):
        nb = min(_POSE_BLOCK, B - b0)
        for j in range(nb):
            _object_to_cameras(T[b0 + j], T_cw, M, j)
        for i in range(points.shape[0]):
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            wi = weights[i]
            for j in range(nb):
                frac = _fraction(px, py, pz, M, j, bound, depth, K, widths, heights, tol, ramp)
                if frac > 0.0:
                    out[b0 + j] += wi * frac
    return out


@kernel(F2, F2, *_VIEWS, nogil=True)
def free_points(T, points, bound, depth, T_cw, K, widths, heights, tol, ramp):  # pragma: no cover
    """Free-space fraction of each point ``(N,)`` at one pose ``T`` (4, 4)."""
    out = np.empty(points.shape[0])
    M = np.empty((1, T_cw.shape[0], 12))
    _object_to_cameras(T, T_cw, M, 0)
    for i in range(points.shape[0]):
        out[i] = _fraction(points[i, 0], points[i, 1], points[i, 2], M, 0, bound, depth, K,
                           widths, heights, tol, ramp)
    return out
