"""Observed free space per pixel of the scene's depth images (eq. (1)'s ``free_space="pixels"``).

The paper's scene "knows empty and unobserved space". The voxel grid
(:class:`~certpose.model.scene.SceneField`'s ``EMPTY`` voxels) is one way to know it; the depth
image it was fused from is the sharper one. A scene point ``q`` (world frame) seen by a view with
camera depth ``z`` at its nearest pixel ``u``:

* stands in **observed free space** by ``d(u) - z`` metres when that is positive, where ``d(u)``
  is the pixel's measured depth, min-filtered over a ``(2 window + 1)``-pixel square so that the
  mixed pixels of a silhouette (depth between foreground and background) do not count the space
  just beside a foreground edge as free;
* is **unobserved** when the pixel has no depth (0), lies outside the image, or ``z <= 0``;
* is **occluded** (behind the measured surface, ``z >= d(u)``): no penalty either.

With several window widths the charge is graded in the image: the mean over the widths. The
silhouettes of YCB-Video's annotated poses stand up to a few pixels past the observed ones (at
the true pose, points charged with a single window of 0 / 5 / 10 / 15 pixels: median 4.0 / 0.7 /
0 / 0% of the model over the 60 frame-object pairs of scenes 0000, 0002, 0049 and 0050; the power
drill 18-19 / 13-14 / 3-6 / 0.2-1%), while a mug's handle turned out of hiding stands 10-30
pixels past the mug's (0000/000001: 24-37 points charged with 10 pixels where the hidden arc has
7-10, 4-19 against 0-4 with 15 pixels).

Eq. (1) charges a point by its free-space fraction
``clip((d(u) - z - tolerance) / ramp, 0, 1)`` (a step at ``tolerance`` when ``ramp`` is 0): the
point then costs ``c_empty`` instead of what unobserved space costs (see
:class:`~certpose.model.likelihood.LikelihoodParams`). With several views the largest fraction
counts (free in any view is free).

The voxel grid measures "how deep in free space" as the Euclidean distance to the nearest voxel
that is not ``EMPTY`` (5-mm voxels, carved 1 cm in front of the depth); here it is measured
along the line of sight at the image's resolution (about 1 mm per pixel at 1 m on YCB-Video).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.jit import compiled
from solvers.validation import as_float_array, check_points

__all__ = ["PixelFreeSpace", "check_windows", "scene_frames"]

log = logging.getLogger(__name__)


def scene_frames(scene: Any) -> tuple[Any, ...]:
    """The RGB-D frames a scene keeps (``SceneField.frames``); a clear error when it keeps none.

    Raises
    ------
    ValueError
        When the scene was not built from depth images (e.g. from a point cloud, or constructed
        directly from arrays): it knows its voxel states but not the pixels.
    """
    frames = tuple(getattr(scene, "frames", ()) or ())
    if not frames:
        raise ValueError(
            "The scene keeps no depth image (`scene.frames` is empty: it was built from arrays or a "
            "point cloud, not by build_scene_field from RGB-D frames), so free space cannot be "
            "tested per pixel; use free_space='voxels'."
        )
    return frames


def check_windows(window: Any) -> tuple[int, ...]:
    """``window`` (an int or a non-empty sequence of ints, each >= 0) as a sorted tuple."""
    items = (window,) if np.ndim(window) == 0 else tuple(window)
    if not items:
        raise ValueError("`window` is empty: give at least one width in pixels.")
    out = []
    for w in items:
        if isinstance(w, (bool, np.bool_)) or int(w) != w or w < 0:
            raise ValueError(f"`window` must be a non-negative integer or a sequence of them "
                             f"(pixels), got {window!r}.")
        out.append(int(w))
    return tuple(sorted(out))


def _rounded_up(depth: NDArray[np.float64]) -> NDArray[np.float32]:
    """``depth`` as float32, each value rounded up where float32 cannot hold it: a bound the
    free-space kernel tests first (``bound >= depth`` holds exactly)."""
    bound = depth.astype(np.float32)
    low = bound.astype(np.float64) < depth
    bound[low] = np.nextafter(bound[low], np.float32(np.inf))
    return np.ascontiguousarray(bound)


class PixelFreeSpace:
    """The per-pixel free-space test of a set of depth views, vectorised over poses and points.

    Parameters
    ----------
    frames : sequence of RGBDFrame
        Posed depth images (``depth`` (H, W) metres, 0 = no depth; ``intrinsics``;
        ``T_world_camera``). Frames may differ in size.
    tolerance : float, optional
        Metres (>= 0). A point less than this in front of the measured depth is not charged
        (depth noise and annotation error; default 1 cm, the voxel grid's default carving margin).
    ramp : float, optional
        Metres (>= 0). Beyond ``tolerance`` the charged fraction rises linearly to 1 over this
        distance (0: a step).
    window : int or sequence of int, optional
        Half-width in pixels (>= 0) of the min-filter applied to the valid depths (0: the nearest
        pixel only). A pixel without depth stays unobserved whatever its neighbours hold. With
        several widths a point's fraction is the mean of the fractions the filtered images give:
        a charge that grows with the point's distance in pixels from where the image could
        show it (e.g. ``(5, 10, 15)``: a third for a point within 5-10 pixels of the silhouette,
        all of it past 15).
    """

    def __init__(self, frames: Sequence[Any], *, tolerance: float = 0.01, ramp: float = 0.0,
                 window: int | Sequence[int] = 15) -> None:
        from scipy.ndimage import minimum_filter

        frames = tuple(frames)
        if not frames:
            raise ValueError("`frames` is empty: at least one depth view is needed.")
        for name, value in (("tolerance", tolerance), ("ramp", ramp)):
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"`{name}` must be a non-negative number of metres, got {value}.")
        self.tolerance, self.ramp = float(tolerance), float(ramp)
        self.windows = check_windows(window)
        self.window = self.windows[0]
        L = len(self.windows)
        H = max(f.depth.shape[0] for f in frames)
        W = max(f.depth.shape[1] for f in frames)
        self._depth = np.zeros((len(frames), H, W, L))  # a pixel's levels side by side
        for k, f in enumerate(frames):
            d0 = np.asarray(f.depth, dtype=np.float64)
            valid = d0 > 0
            for lv, w in enumerate(self.windows):
                d = d0
                if w > 0:
                    low = minimum_filter(np.where(valid, d0, np.inf), size=2 * w + 1, mode="nearest")
                    d = np.where(valid, low, 0.0)
                self._depth[k, : d.shape[0], : d.shape[1], lv] = d
        self._bound = _rounded_up(self._depth[..., 0])
        self._T_cw = np.ascontiguousarray(np.stack([np.linalg.inv(f.T_world_camera) for f in frames]))
        self._K = np.array([[f.intrinsics.fx, f.intrinsics.fy, f.intrinsics.cx, f.intrinsics.cy]
                            for f in frames], dtype=np.float64)
        self._widths = np.array([f.intrinsics.width for f in frames], dtype=np.int64)
        self._heights = np.array([f.intrinsics.height for f in frames], dtype=np.int64)

    @classmethod
    def from_scene(cls, scene: Any, **kwargs: Any) -> PixelFreeSpace:
        """The test on the depth images a scene was built from (:func:`scene_frames`)."""
        return cls(scene_frames(scene), **kwargs)

    def _views(self) -> tuple[Any, ...]:
        return (self._bound, self._depth, self._T_cw, self._K, self._widths, self._heights,
                self.tolerance, self.ramp)

    def weighted_sum(self, T: NDArray[np.float64], points: NDArray[np.float64],
                     weights: NDArray[np.float64], *, kernel: Any = None) -> NDArray[np.float64]:
        """``sum_i w_i frac_i`` (B,) for the poses ``T`` (B, 4, 4) (C-contiguous float64) of the
        object points (N, 3) with weights (N,); ``frac_i`` in [0, 1] is the point's free-space
        fraction (the numba kernel behind eq. (1); no input checks). ``kernel``:
        :meth:`batch_kernel`, loaded beforehand by a caller that runs this on worker threads."""
        return (kernel or self.batch_kernel())(T, points, weights, *self._views())

    @staticmethod
    def batch_kernel() -> Any:
        """The compiled batch kernel. Load it on the calling thread before handing batches to
        worker threads: loading the kernel module from several threads at once can see it
        half-imported (``AttributeError: partially initialized module``)."""
        return compiled("certpose.model._freespace_kernels").free_batch

    def fractions(self, T: ArrayLike, points: ArrayLike) -> NDArray[np.float64]:
        """Free-space fraction (N,) of each object point at one pose ``T`` (4, 4)."""
        T = as_float_array(T, "T")
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"Expected `T` to have shape (4, 4) and be finite, got {T.shape}.")
        p = check_points(points, "points", min_points=0)
        return compiled("certpose.model._freespace_kernels").free_points(
            np.ascontiguousarray(T), np.ascontiguousarray(p, dtype=np.float64), *self._views())

    def depth(self, points: ArrayLike) -> NDArray[np.float64]:
        """How deep each scene point (N, 3) (world frame) stands in observed free space, metres.

        ``d(u) - z`` maximised over the views (``d`` min-filtered, see the class); 0 where no view
        sees the point in front of a measured depth (unobserved or occluded). The plain numpy
        form of the test, without ``tolerance`` and ``ramp``
        (:func:`~certpose.model.arc.free_space_arc` uses it).
        """
        q = check_points(points, "points", min_points=0)
        out = np.zeros(q.shape[0])
        for k in range(self._T_cw.shape[0]):
            c = q @ self._T_cw[k, :3, :3].T + self._T_cw[k, :3, 3]
            z = c[:, 2]
            ok = z > 1e-9
            fx, fy, cx, cy = self._K[k]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = np.floor(fx * c[:, 0] / z + cx + 0.5)
                v = np.floor(fy * c[:, 1] / z + cy + 0.5)
            ok &= (u >= 0) & (v >= 0) & (u < self._widths[k]) & (v < self._heights[k])
            d = np.zeros(q.shape[0])
            d[ok] = self._depth[k, v[ok].astype(np.int64), u[ok].astype(np.int64), 0]
            seen = ok & (d > 0)
            out[seen] = np.maximum(out[seen], d[seen] - z[seen])
        return out
