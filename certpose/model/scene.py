"""The scene field ``f_scn``: a voxel grid of fused descriptors with empty/unobserved states.

Grid conventions: voxel ``(i, j, k)`` covers ``origin + [i, i+1) x [j, j+1) x [k, k+1)`` times
``voxel_size`` and has its centre at ``origin + (ijk + 0.5) * voxel_size``. Continuous grid
coordinates (:meth:`SceneField.world_to_grid`) put voxel centres at integers. Flat indices are
C-order (``np.ravel_multi_index`` over ``shape``).

States (paper section 1; an empty voxel has ``z^T z_emp = -inf``, an unobserved one
``z^T z_null = 0``):

* ``OCCUPIED``: a measured surface point fell into the voxel; its descriptor is the re-normalised
  mean of those points' descriptors.
* ``EMPTY`` (``z_emp``): observed free space, i.e. the voxel centre lies in front of the measured
  surface of some frame by more than ``free_space_margin``.
* ``UNOBSERVED`` (``z_null``): everything else (behind surfaces, outside every image, invalid
  depth, near a surface without points), and everything outside the grid.

Only occupied voxels carry a descriptor; the others hold zeros, so trilinear interpolation treats
them as ``z_null`` (inner product 0).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from certpose.geometry.features import (
    ArrayBackbone,
    FPFHBackbone,
    resolve_backbone,
)
from certpose.geometry.rgbd import (
    CameraIntrinsics,
    RGBDFrame,
    check_descriptors,
    check_mask,
    group_voxels,
    normalize_rows,
    sum_by_group,
)
from certpose.model.grid import EMPTY, OCCUPIED, UNOBSERVED, VOXEL_CENTRE_OFFSET, GridSpec
from solvers.lie import invert_transform
from solvers.validation import as_float_array, check_points

__all__ = [
    "SceneField",
    "build_scene_field",
    "bounds_from_points",
]

log = logging.getLogger(__name__)


# Corner offsets of the trilinear stencil, shape (8, 3).
_CORNERS = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=np.int64)


@dataclass(frozen=True, eq=False)
class SceneField:
    """A voxel grid of descriptors with the states ``UNOBSERVED``, ``EMPTY``, ``OCCUPIED``.

    Parameters
    ----------
    voxel_size : float
        Voxel side in metres.
    origin : ndarray, shape (3,)
        World coordinates of the outer corner of voxel ``(0, 0, 0)``, metres.
    shape : tuple of int
        Grid size ``(X, Y, Z)``.
    descriptors : ndarray, shape (X, Y, Z, d), float32 or float64
        Unit descriptors of occupied voxels, zero elsewhere.
    state : ndarray of int8, shape (X, Y, Z)
        ``UNOBSERVED`` (0), ``EMPTY`` (1) or ``OCCUPIED`` (2).
    backbone : FeatureBackbone, optional
        The backbone that produced the descriptors (possibly fitted to this scene, see
        :func:`build_scene_field`); object descriptors must come from the same one.
    frames : tuple of RGBDFrame, optional
        The posed depth images the field was fused from (:func:`build_scene_field` keeps them):
        eq. (1)'s per-pixel free-space test (``LikelihoodParams.free_space="pixels"``,
        :mod:`certpose.model.freespace`) reads them. Empty for a field built from arrays.
    """

    voxel_size: float
    origin: NDArray[np.float64]
    shape: tuple[int, int, int]
    descriptors: NDArray[np.floating]
    state: NDArray[np.int8]
    backbone: Any = field(default=None, compare=False, repr=False)
    frames: tuple[RGBDFrame, ...] = field(default=(), compare=False, repr=False)

    def __post_init__(self) -> None:
        frames = tuple(self.frames or ())
        for i, f in enumerate(frames):
            if not isinstance(f, RGBDFrame):
                raise TypeError(f"`frames[{i}]` must be an RGBDFrame, got {type(f).__name__}.")
        object.__setattr__(self, "frames", frames)
        vs = float(self.voxel_size)
        if not (np.isfinite(vs) and vs > 0):
            raise ValueError(f"`voxel_size` must be positive and finite, got {self.voxel_size}.")
        object.__setattr__(self, "voxel_size", vs)
        origin = as_float_array(self.origin, "origin")
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise ValueError(f"Expected `origin` to have shape (3,) and be finite, got {origin.shape}.")
        origin.setflags(write=False)
        object.__setattr__(self, "origin", origin)
        shape = tuple(int(s) for s in self.shape)
        if len(shape) != 3 or min(shape) < 1:
            raise ValueError(f"Expected `shape` to be 3 positive integers, got {self.shape}.")
        object.__setattr__(self, "shape", shape)
        desc = np.asarray(self.descriptors)
        if desc.dtype not in (np.float32, np.float64):
            desc = desc.astype(np.float64)
        if desc.ndim != 4 or desc.shape[:3] != shape:
            raise ValueError(f"Expected `descriptors` to have shape {(*shape, 'd')}, got {desc.shape}.")
        state = np.asarray(self.state)
        if state.shape != shape:
            raise ValueError(f"Expected `state` to have shape {shape}, got {state.shape}.")
        if not np.issubdtype(state.dtype, np.integer):
            raise TypeError(f"`state` must have an integer dtype, got {state.dtype}.")
        if not np.all((state >= UNOBSERVED) & (state <= OCCUPIED)):
            raise ValueError("`state` holds values other than UNOBSERVED (0), EMPTY (1), OCCUPIED (2).")
        state = state.astype(np.int8, copy=False)
        occupied = desc[state == OCCUPIED]
        # NaN and inf are non-zero: once every non-zero entry is known to sit in an occupied
        # voxel, finiteness only needs checking there (cheap on large, mostly empty grids).
        if np.count_nonzero(desc) != np.count_nonzero(occupied):
            raise ValueError("`descriptors` must be zero at voxels that are not OCCUPIED.")
        if not np.all(np.isfinite(occupied)):
            raise ValueError("`descriptors` contains NaN or inf values.")
        # Read-only views: the field is immutable without copying (or freezing) the caller's arrays.
        desc, state = desc.view(), state.view()
        desc.setflags(write=False)
        state.setflags(write=False)
        object.__setattr__(self, "descriptors", desc)
        object.__setattr__(self, "state", state)

    # ----------------------------------------------------------------- basics
    @property
    def dim(self) -> int:
        """Descriptor dimension ``d``."""
        return int(self.descriptors.shape[3])

    @property
    def n_voxels(self) -> int:
        """``X * Y * Z``."""
        return int(np.prod(self.shape))

    @property
    def grid(self) -> GridSpec:
        """The grid's geometry (voxel centres, continuous coordinates)."""
        return GridSpec(self.origin, self.voxel_size, self.shape, VOXEL_CENTRE_OFFSET)

    @property
    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World-frame box ``(min (3,), max (3,))`` covered by the grid, metres."""
        return self.origin.copy(), self.origin + np.asarray(self.shape) * self.voxel_size

    def counts(self) -> dict[str, int]:
        """Number of voxels in each state."""
        c = np.bincount(self.state.ravel(), minlength=3)
        return {"unobserved": int(c[UNOBSERVED]), "empty": int(c[EMPTY]), "occupied": int(c[OCCUPIED])}

    def world_to_grid(self, points: ArrayLike) -> NDArray[np.float64]:
        """Continuous grid coordinates ``(N, 3)``; voxel centres map to integers."""
        return self.grid.to_grid(check_points(points, "points", min_points=0))

    def grid_to_world(self, ijk: ArrayLike) -> NDArray[np.float64]:
        """World coordinates ``(N, 3)`` of (continuous) grid coordinates; inverse of :meth:`world_to_grid`."""
        g = as_float_array(ijk, "ijk")
        if g.ndim != 2 or g.shape[1] != 3:
            raise ValueError(f"Expected `ijk` to have shape (N, 3), got {g.shape}.")
        return self.grid.centres(g)

    def voxel_index(self, points: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """Integer index ``(N, 3)`` of the voxel containing each point, and whether it is in the grid."""
        ijk = self.grid.voxel_of(check_points(points, "points", min_points=0))
        return ijk, self.grid.inside(ijk)

    # ---------------------------------------------------------------- queries
    def state_at(self, points: ArrayLike) -> NDArray[np.int8]:
        """State of the voxel containing each point, shape ``(N,)``; ``UNOBSERVED`` outside the grid."""
        ijk, inside = self.voxel_index(points)
        out = np.full(ijk.shape[0], UNOBSERVED, dtype=np.int8)
        out[inside] = self.state[ijk[inside, 0], ijk[inside, 1], ijk[inside, 2]]
        return out

    def trilinear_weights(self, points: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """The 8-corner trilinear stencil of each point over voxel centres.

        Returns
        -------
        flat : ndarray of int64, shape (N, 8)
            Flat voxel indices of the corners; corners outside the grid get ``n_voxels`` (one
            past the end) so that a table padded with one zero row can be indexed directly.
        weights : ndarray, shape (N, 8)
            Trilinear weights (sum 1; 0 for corners outside the grid).
        """
        g = self.world_to_grid(points)
        i0 = np.floor(g)
        frac = g - i0
        i0 = i0.astype(np.int64)
        idx = i0[:, None, :] + _CORNERS[None, :, :]  # (N, 8, 3)
        w = np.prod(np.where(_CORNERS[None, :, :] == 1, frac[:, None, :], 1.0 - frac[:, None, :]), axis=2)
        shape = np.asarray(self.shape)
        inside = np.all((idx >= 0) & (idx < shape), axis=2)
        strides = np.array([shape[1] * shape[2], shape[2], 1], dtype=np.int64)
        flat = np.where(inside, idx @ strides, self.n_voxels)
        return flat, np.where(inside, w, 0.0)

    def interpolate(self, points: ArrayLike) -> NDArray[np.float64]:
        """``f_scn`` at continuous points: trilinear interpolation over voxel centres.

        Non-occupied corners (and corners outside the grid) contribute zero (``z_null``).

        Parameters
        ----------
        points : array_like, shape (N, 3)
            World-frame points, metres.

        Returns
        -------
        ndarray, shape (N, d)
        """
        flat, w = self.trilinear_weights(points)
        table = self.descriptors.reshape(-1, self.dim)
        out = np.zeros((flat.shape[0], self.dim))
        for c in range(8):
            keep = w[:, c] > 0
            if keep.any():
                out[keep] += w[keep, c, None] * table[flat[keep, c]]
        return out

    def occupied_index(self) -> NDArray[np.int64]:
        """Flat indices (sorted) of the occupied voxels, shape ``(M,)``."""
        return np.flatnonzero(self.state.ravel() == OCCUPIED)

    def occupied_centers(self) -> NDArray[np.float64]:
        """World coordinates of the occupied voxel centres, shape ``(M, 3)``, in :meth:`occupied_index` order."""
        ijk = np.stack(np.unravel_index(self.occupied_index(), self.shape), axis=1)
        return self.grid_to_world(ijk)

    def occupied_descriptors(self) -> NDArray[np.float64]:
        """Descriptors of the occupied voxels, shape ``(M, d)``, in :meth:`occupied_index` order."""
        return self.descriptors.reshape(-1, self.dim)[self.occupied_index()].astype(np.float64)

    def occupied_lookup(self) -> NDArray[np.int64]:
        """Map flat voxel index -> row in :meth:`occupied_index` (``-1`` if not occupied), shape ``(X*Y*Z,)``."""
        lookup = np.full(self.n_voxels, -1, dtype=np.int64)
        occ = self.occupied_index()
        lookup[occ] = np.arange(occ.size)
        return lookup

    def save(self, path: str | Path) -> None:
        """Write the field to a compressed ``.npz`` file (an FPFH backbone's settings and the
        frames' depth images and cameras included)."""
        extra = {}
        if isinstance(self.backbone, FPFHBackbone):
            extra["fpfh"] = np.array(json.dumps(asdict(self.backbone)))
        # The depth images (not the colour) for the per-pixel free-space test.
        for k, f in enumerate(self.frames):
            K = f.intrinsics
            extra[f"frame{k}_depth"] = f.depth
            extra[f"frame{k}_camera"] = np.array([K.fx, K.fy, K.cx, K.cy, K.width, K.height])
            extra[f"frame{k}_T_world_camera"] = f.T_world_camera
        np.savez_compressed(
            Path(path),
            voxel_size=self.voxel_size,
            origin=self.origin,
            descriptors=self.descriptors,
            state=self.state,
            **extra,
        )

    @classmethod
    def load(cls, path: str | Path) -> SceneField:
        """Read a field written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"The scene field file {path} does not exist.")
        import zipfile

        if not zipfile.is_zipfile(path):  # np.load would return a bare array for a .npy file
            raise ValueError(f"Cannot read a scene field from {path}: not a .npz archive "
                             "(truncated, or another format).")
        try:
            with np.load(path, allow_pickle=False) as data:
                backbone = None
                if "fpfh" in data:
                    backbone = FPFHBackbone(**json.loads(str(data["fpfh"])))
                state = data["state"]
                frames = []
                while f"frame{len(frames)}_depth" in data:
                    k = len(frames)
                    fx, fy, cx, cy, w, h = data[f"frame{k}_camera"]
                    frames.append(RGBDFrame(None, data[f"frame{k}_depth"],
                                            CameraIntrinsics(fx, fy, cx, cy, int(w), int(h)),
                                            data[f"frame{k}_T_world_camera"]))
                return cls(
                    float(data["voxel_size"]), data["origin"], state.shape, data["descriptors"], state,
                    backbone=backbone, frames=tuple(frames),
                )
        except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
            raise ValueError(f"Cannot read a scene field from {path}: {exc}") from exc

    def to_open3d(self) -> Any:
        """Occupied voxel centres as an ``open3d.geometry.PointCloud`` (for viewing)."""
        import open3d as o3d

        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.occupied_centers()))


def bounds_from_points(
    points: ArrayLike, *, margin: float = 0.02
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Axis-aligned box ``(min, max)`` of ``points`` (N, 3) grown by ``margin`` metres."""
    p = check_points(points, "points")
    if not margin >= 0:
        raise ValueError(f"`margin` must be non-negative, got {margin}.")
    return p.min(axis=0) - margin, p.max(axis=0) + margin


def _check_bounds(bounds: Any) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    try:
        lo, hi = bounds
    except (TypeError, ValueError) as exc:
        raise ValueError("`bounds` must be a pair (min (3,), max (3,)).") from exc
    lo = as_float_array(lo, "bounds[0]")
    hi = as_float_array(hi, "bounds[1]")
    for name, arr in (("bounds[0]", lo), ("bounds[1]", hi)):
        if arr.shape != (3,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"Expected `{name}` to have shape (3,) and be finite, got {arr.shape}.")
    if np.any(hi <= lo):
        raise ValueError(f"`bounds` max must exceed min on every axis, got {lo.tolist()} and {hi.tolist()}.")
    return lo, hi


def _as_frames(frames: Any) -> list[RGBDFrame]:
    if isinstance(frames, RGBDFrame):
        return [frames]
    frames = list(frames)
    if not frames:
        raise ValueError("`frames` is empty: at least one RGBDFrame is needed.")
    for i, f in enumerate(frames):
        if not isinstance(f, RGBDFrame):
            raise TypeError(f"`frames[{i}]` must be an RGBDFrame, got {type(f).__name__}.")
    return frames


def _per_frame_masks(roi_mask: Any, frames: list[RGBDFrame]) -> list[NDArray[np.bool_] | None]:
    if roi_mask is None:
        return [None] * len(frames)
    if isinstance(roi_mask, np.ndarray) and roi_mask.ndim == 2:
        masks = [roi_mask] + [None] * (len(frames) - 1)
    else:
        masks = list(roi_mask)
        if len(masks) != len(frames):
            raise ValueError(f"Expected {len(frames)} ROI masks (one per frame), got {len(masks)}.")
    return [
        None if m is None else check_mask(m, f"roi_mask[{i}]", f.shape)
        for i, (m, f) in enumerate(zip(masks, frames, strict=True))
    ]


def _per_frame_backbones(backbone_or_descriptors: Any, n: int) -> list[Any]:
    if isinstance(backbone_or_descriptors, (list, tuple)) and len(backbone_or_descriptors) == n and all(
        isinstance(x, np.ndarray) for x in backbone_or_descriptors
    ):
        return [ArrayBackbone(x) for x in backbone_or_descriptors]
    backbone = resolve_backbone(backbone_or_descriptors)
    if isinstance(backbone, FPFHBackbone) and backbone.viewpoint != (0.0, 0.0, 0.0):
        # Scene points are described in their camera frame: orient normals towards the camera.
        backbone = replace(backbone, viewpoint=(0.0, 0.0, 0.0))
    return [backbone] * n


def build_scene_field(
    frames: RGBDFrame | Sequence[RGBDFrame],
    backbone_or_descriptors: Any = None,
    *,
    voxel_size: float = 0.005,
    bounds: tuple[ArrayLike, ArrayLike] | None = None,
    roi_mask: ArrayLike | Sequence[ArrayLike | None] | None = None,
    margin: float = 0.05,
    free_space_margin: float | None = None,
    dtype: type = np.float32,
    max_voxels: int = 20_000_000,
    fit_backbone: bool = False,
) -> SceneField:
    """Fuse posed RGB-D frames into a :class:`SceneField` (world frame).

    Parameters
    ----------
    frames : RGBDFrame or sequence of RGBDFrame
        Posed frames (``T_world_camera``; world = camera of the first frame when it is the
        identity). Frame masks are ignored here (use ``roi_mask`` to crop).
    backbone_or_descriptors : FeatureBackbone, array, list of arrays or None
        ``None``: default :class:`~certpose.geometry.features.FPFHBackbone`. A point backbone describes,
        per frame, the camera-frame points averaged per voxel (with the backbone's ``radius`` of
        context around the grid; FPFH normals are oriented towards the camera). An image backbone or per-pixel descriptor array ``(H, W, d)``
        (a list: one per frame) gives each pixel a descriptor, averaged per voxel.
    voxel_size : float, optional
        Voxel side in metres (default 5 mm).
    bounds : (array_like (3,), array_like (3,)), optional
        World-frame box of the grid. Default: the bounding box of the observed points (those in
        ``roi_mask`` when given) grown by ``margin``.
    roi_mask : array_like of bool (H, W), or a sequence (one per frame, None allowed), optional
        Region of interest used for the default bounds (e.g. an object mask).
    margin : float, optional
        Growth of the default bounds, metres (default 5 cm). Outside the grid everything is
        UNOBSERVED, so the margin bounds how far a pose hypothesis can move off the observed
        surface and still see the free space it violates.
    free_space_margin : float, optional
        A voxel is EMPTY when its centre lies in front of the measured depth by more than this
        (default ``2 * voxel_size``), so surface noise does not carve free space.
    dtype : numpy float type, optional
        Storage type of the descriptors (float32 halves memory).
    max_voxels : int, optional
        Refuse larger grids (crop with ``bounds``/``roi_mask`` or use larger voxels).
    fit_backbone : bool, optional
        With an :class:`~certpose.geometry.features.FPFHBackbone` that has no ``center`` yet, centre the
        descriptors on this scene's mean histogram (see its docstring; recommended: on
        YCB-Video it separates true from random poses about twice as well). The backbone
        actually used is returned as ``SceneField.backbone``: describe the object with *it*,
        not with the backbone passed in. Off by default so that the backbone passed in is the
        one used.

    Returns
    -------
    SceneField
    """
    frames = _as_frames(frames)
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise ValueError(f"`voxel_size` must be positive and finite, got {voxel_size}.")
    if free_space_margin is None:
        free_space_margin = 2.0 * voxel_size
    if not free_space_margin >= 0:
        raise ValueError(f"`free_space_margin` must be non-negative, got {free_space_margin}.")
    if np.dtype(dtype) not in (np.float32, np.float64):
        raise ValueError(f"`dtype` must be float32 or float64, got {dtype}.")
    backbones = _per_frame_backbones(backbone_or_descriptors, len(frames))
    masks = _per_frame_masks(roi_mask, frames)

    clouds = []  # per frame: camera points, world points, pixels
    for f in frames:
        p_cam, px = f.backproject(mask=False)
        R, t = f.T_world_camera[:3, :3], f.T_world_camera[:3, 3]
        # The camera is often the world (one frame): p @ I + 0 == p, bit for bit.
        identity = np.array_equal(f.T_world_camera, np.eye(4))
        clouds.append((p_cam, p_cam if identity else p_cam @ R.T + t, px))

    if bounds is None:
        sel = []
        for (_, p_w, px), m in zip(clouds, masks, strict=True):
            sel.append(p_w if m is None else p_w[m[px[:, 0], px[:, 1]]])
        sel_pts = np.concatenate(sel)
        if sel_pts.shape[0] == 0:
            raise ValueError("`roi_mask` selects no pixel with valid depth: cannot place the grid.")
        lo, hi = bounds_from_points(sel_pts, margin=margin)
    else:
        lo, hi = _check_bounds(bounds)
    shape = tuple(int(s) for s in np.maximum(np.ceil((hi - lo) / voxel_size - 1e-9), 1).astype(int))
    n_vox = int(np.prod(shape))
    if max(shape) < 4:
        raise ValueError(
            f"`voxel_size` {voxel_size} m is too coarse for a region {np.round(hi - lo, 3).tolist()} m "
            f"across (a grid of shape {shape}); use a smaller `voxel_size` (metres)."
        )
    if n_vox > max_voxels:
        raise ValueError(
            f"The grid would have shape {shape} ({n_vox} voxels > max_voxels={max_voxels}); crop it "
            "with `bounds` or `roi_mask`, or use a larger `voxel_size`."
        )
    grid = GridSpec(lo, float(voxel_size), shape, VOXEL_CENTRE_OFFSET)

    # --- occupied voxels: mean descriptor of their points, fused over frames
    per_frame = [
        _frame_voxels(f, b, p_cam, p_w, px, grid)
        for f, b, (p_cam, p_w, px) in zip(frames, backbones, clouds, strict=True)
    ]
    shared = backbones[0]
    if (
        fit_backbone
        and isinstance(shared, FPFHBackbone)
        and shared.center is None
        and all(b is shared for b in backbones)
    ):
        hists = [
            shared.histograms(v.points, rows=np.flatnonzero(v.keep)) if v.points is not None
            else np.zeros((0, 33))
            for v in per_frame
        ]
        shared = shared.fit_center(np.concatenate(hists))
        backbones = [shared] * len(frames)
        descs = [shared.finish(h, colors=None if v.colors is None else v.colors[v.keep])
                 for h, v in zip(hists, per_frame, strict=True)]
    else:
        descs = [v.describe(b) for v, b in zip(per_frame, backbones, strict=True)]
    keys_all, sums_all, counts_all = [], [], []
    for v, desc in zip(per_frame, descs, strict=True):
        desc = check_descriptors(desc, "descriptors", int(np.count_nonzero(v.keep)))
        keys_all.append(v.keys[v.keep])
        sums_all.append(desc * v.counts[v.keep, None])
        counts_all.append(v.counts[v.keep])
    keys = np.concatenate(keys_all)
    if keys.shape[0] == 0:
        raise ValueError("No observed point falls inside the grid bounds.")
    uniq, inverse, _ = group_voxels(keys)
    sums = sum_by_group(inverse, np.concatenate(sums_all), uniq.shape[0])
    weight = np.bincount(inverse, weights=np.concatenate(counts_all), minlength=uniq.shape[0])
    fused = normalize_rows(sums / weight[:, None]) if sums.shape[1] else sums
    d = fused.shape[1]
    descriptors = np.zeros((*shape, d), dtype=dtype)
    descriptors[uniq[:, 0], uniq[:, 1], uniq[:, 2]] = fused
    state = np.full(shape, UNOBSERVED, dtype=np.int8)

    # --- free space: project every voxel centre into every frame (vectorised)
    empty = np.zeros(shape, dtype=bool)
    for f in frames:
        empty |= _in_front_of_surface(f, grid, free_space_margin)
    state[empty] = EMPTY
    state[uniq[:, 0], uniq[:, 1], uniq[:, 2]] = OCCUPIED  # a measured point wins over free space
    scene = SceneField(voxel_size, grid.origin, shape, descriptors, state, backbone=backbones[0],
                       frames=tuple(frames))
    log.debug("scene field %s: %s", shape, scene.counts())
    return scene


def _in_front_of_surface(
    frame: RGBDFrame,
    grid: GridSpec,
    margin: float,
) -> NDArray[np.bool_]:
    """Whether each voxel centre lies in front of the frame's measured surface by more than ``margin``.

    Each centre is projected to its nearest pixel and compared with that pixel's depth. Camera
    coordinates are affine in the voxel index, so they are summed from per-axis terms
    (broadcast over the grid) instead of transforming millions of centres.
    """
    T = invert_transform(frame.T_world_camera)
    R, t = T[:3, :3], T[:3, 3]
    axes = grid.axes()
    shape = grid.shape
    K = frame.intrinsics
    depth = frame.depth.reshape(-1)
    out = np.zeros(shape, dtype=bool)
    step = max(1, (1 << 21) // (shape[1] * shape[2]))  # bound the temporaries (~2M voxels)
    for i0 in range(0, shape[0], step):
        xs = axes[0][i0 : i0 + step]
        cam = [
            R[r, 0] * xs[:, None, None] + R[r, 1] * axes[1][None, :, None] + (R[r, 2] * axes[2] + t[r])[None, None, :]
            for r in range(3)
        ]
        z = cam[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(K.fx * cam[0] / z + K.cx)
            v = np.rint(K.fy * cam[1] / z + K.cy)
        inside = (z > 1e-9) & (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
        measured = np.zeros(z.shape)
        measured[inside] = depth[v[inside].astype(np.int64) * K.width + u[inside].astype(np.int64)]
        # Invalid depth (0) says nothing about free space.
        out[i0 : i0 + step] = inside & (measured > 0) & (z < measured - margin)
    return out


@dataclass
class _FrameVoxels:
    """One frame's points averaged per voxel (``keep``: inside the grid, not just the context)."""

    keys: NDArray[np.int64]
    keep: NDArray[np.bool_]
    counts: NDArray[np.float64]
    points: NDArray[np.float64] | None = None  # camera frame, for point backbones
    colors: NDArray[np.float64] | None = None
    descriptors: NDArray[np.float64] | None = None  # for image backbones

    def describe(self, backbone: Any) -> NDArray[np.float64]:
        """Descriptors of the kept voxels, shape ``(keep.sum(), d)``."""
        if self.descriptors is not None:
            return check_descriptors(self.descriptors, "descriptors", self.keep.shape[0])[self.keep]
        if isinstance(backbone, FPFHBackbone):
            # Only the kept voxels' FPFH: the context voxels serve as their neighbours.
            return backbone.describe(self.points, colors=self.colors, rows=np.flatnonzero(self.keep))
        desc = backbone.describe(self.points, colors=self.colors)
        return check_descriptors(desc, "descriptors", self.keep.shape[0])[self.keep]


def _frame_voxels(
    frame: RGBDFrame,
    backbone: Any,
    p_cam: NDArray[np.float64],
    p_world: NDArray[np.float64],
    pixels: NDArray[np.int64],
    grid: GridSpec,
) -> _FrameVoxels:
    """Group one frame's points by voxel (means of points, colours or per-pixel descriptors)."""
    keys = grid.voxel_of(p_world)
    shape, voxel_size = np.asarray(grid.shape), grid.voxel_size
    image_backbone = hasattr(backbone, "describe_image") and getattr(backbone, "per_pixel", True)
    if image_backbone:
        image = np.asarray(backbone.describe_image(frame.color, frame.shape))
        if image.ndim != 3 or image.shape[:2] != frame.shape:
            raise ValueError(
                f"Expected per-pixel descriptors of shape {(*frame.shape, 'd')}, got {image.shape}."
            )
        in_grid = np.all((keys >= 0) & (keys < shape), axis=1)
        if not in_grid.any():
            return _FrameVoxels(np.zeros((0, 3), np.int64), np.zeros(0, bool), np.zeros(0),
                                descriptors=np.zeros((0, image.shape[2])))
        desc = check_descriptors(image[pixels[in_grid, 0], pixels[in_grid, 1]], "descriptors")
        uniq, inverse, counts = group_voxels(keys[in_grid])
        sums = sum_by_group(inverse, desc, uniq.shape[0])
        return _FrameVoxels(uniq, np.ones(uniq.shape[0], bool), counts.astype(np.float64),
                            descriptors=sums / counts[:, None])
    # Point backbone: describe voxel-averaged points, with the backbone's support radius of
    # context around the grid so border voxels see their whole neighbourhood.
    pad = int(np.ceil(float(getattr(backbone, "radius", 0.0)) / voxel_size))
    near = np.all((keys >= -pad) & (keys < shape + pad), axis=1)
    uniq, inverse, counts = group_voxels(keys[near])
    m = uniq.shape[0]
    mean_cam = sum_by_group(inverse, p_cam[near], m) / counts[:, None]
    colors = frame.colors_at(pixels[near])
    mean_col = None if colors is None else np.clip(sum_by_group(inverse, colors, m) / counts[:, None], 0, 1)
    keep = np.all((uniq >= 0) & (uniq < shape), axis=1)
    if not keep.any():  # this frame does not see the grid
        return _FrameVoxels(np.zeros((0, 3), np.int64), np.zeros(0, bool), np.zeros(0),
                            descriptors=np.zeros((0, int(getattr(backbone, "dim", 0)))))
    return _FrameVoxels(uniq, keep, counts.astype(np.float64), points=mean_cam, colors=mean_col)
