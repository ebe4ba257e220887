"""RGB-D input: camera intrinsics, posed frames, back-projection and structured point clouds.

Camera frame convention (OpenCV): x right, y down, z forward; pixel ``(row v, col u)`` has its
centre at image coordinates ``(u, v)``, so a point ``(x, y, z)`` projects to
``u = fx x / z + cx``, ``v = fy y / z + cy``. Depth is the z coordinate in metres; 0 marks an
invalid measurement.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.lie import transform_points
from solvers.validation import as_float_array, check_points, check_transform

if TYPE_CHECKING:
    import open3d as o3d

__all__ = [
    "CameraIntrinsics",
    "RGBDFrame",
    "StructuredPointCloud",
    "backproject",
    "load_rgbd",
    "read_image",
    "read_mask",
    "check_mask",
    "normalize_rows",
    "check_descriptors",
    "group_voxels",
    "sum_by_group",
]

log = logging.getLogger(__name__)

# Larger depths are taken for raw sensor units (millimetres and the like), not metres.
MAX_DEPTH = 100.0


def normalize_rows(x: NDArray[np.floating], *, eps: float = 1e-12) -> NDArray[np.float64]:
    """L2-normalise the rows of ``x`` (shape ``(N, d)``); all-zero rows stay zero."""
    x = np.asarray(x, dtype=np.float64)
    norms = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, norms, out=np.zeros_like(x), where=norms > eps)


def check_descriptors(
    value: Any, name: str, n: int | None = None, *, unit_norm: bool = True, min_dim: int = 1
) -> NDArray[np.float64]:
    """Validate an ``(N, d)`` float array of descriptors, ``N == n`` when given.

    Rows must be finite; with ``unit_norm`` (the default: what eq. (1) assumes) their L2 norm
    must be at most 1 (normalised rows, or 0 for "no information"); ``d >= min_dim``.
    """
    arr = as_float_array(value, name)
    if arr.ndim != 2 or (n is not None and arr.shape[0] != n):
        expected = f"({n}, d)" if n is not None else "(N, d)"
        raise ValueError(f"Expected `{name}` to have shape {expected}, got {arr.shape}.")
    if arr.shape[1] < min_dim:
        raise ValueError(f"Expected `{name}` to have at least {min_dim} column(s), got shape {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr).all(axis=1)))
        raise ValueError(f"`{name}` contains NaN or inf values in {bad} row(s).")
    if unit_norm and arr.size:
        top = float(np.linalg.norm(arr, axis=1).max())
        if top > 1.0 + 1e-6:
            raise ValueError(
                f"`{name}` rows must be L2-normalised (norm <= 1), got a maximum norm of {top:.4g}."
            )
    return arr


def group_voxels(
    keys: NDArray[np.integer],
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Group integer voxel keys: the distinct rows, each key's group, and the group sizes.

    Parameters
    ----------
    keys : ndarray of int, shape (N, 3)
        Voxel indices (any sign).

    Returns
    -------
    rows : ndarray of int64, shape (M, 3)
        The distinct keys in lexicographic order (as ``np.unique(keys, axis=0)``).
    inverse : ndarray of int64, shape (N,)
        ``rows[inverse] == keys``.
    counts : ndarray of int64, shape (M,)
    """
    keys = np.asarray(keys, dtype=np.int64)
    if keys.shape[0] == 0:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    lo = keys.min(axis=0)
    span = tuple(int(s) for s in keys.max(axis=0) - lo + 1)
    if np.prod(np.asarray(span, dtype=np.float64)) >= 2.0**62:  # flat codes would overflow
        rows, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        return rows, inverse.reshape(-1), counts
    # Rows encoded as flat indices (lexicographic order kept): a 1-D np.unique is much faster.
    flat = np.ravel_multi_index((keys - lo).T, span)
    size = int(np.prod(span))
    if size <= min(1 << 22, 64 * keys.shape[0]):
        # Few cells for the keys (a frame's points around a scene's grid): counting per cell
        # gives np.unique's three results without its sort (measured: 18 -> 3 ms, 100k keys).
        per_cell = np.bincount(flat, minlength=size)
        uniq = np.flatnonzero(per_cell)
        counts = per_cell[uniq]
        rank = np.zeros(size, dtype=np.int64)
        rank[uniq] = np.arange(uniq.size)
        inverse = rank[flat]
    else:
        uniq, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    rows = np.stack(np.unravel_index(uniq, span), axis=1).astype(np.int64) + lo
    return rows, inverse.reshape(-1), counts


def sum_by_group(inverse: NDArray[np.int64], values: NDArray[np.floating], m: int) -> NDArray[np.float64]:
    """Row sums of ``values`` (N, d) per group ``inverse`` (N,) of :func:`group_voxels`, shape (m, d)."""
    vals = np.asarray(values, dtype=np.float64)
    out = np.empty((m, vals.shape[1]))
    # One bincount per column: the same sums in the same order as np.add.at (each group's
    # values added one by one in input order), several times faster.
    for j in range(vals.shape[1]):
        out[:, j] = np.bincount(inverse, weights=vals[:, j], minlength=m)
    return out


def check_mask(value: Any, name: str, shape: tuple[int, int], *, allow_empty: bool = False) -> NDArray[np.bool_]:
    """Validate an ``(H, W)`` boolean mask; an all-False mask is an error unless ``allow_empty``."""
    arr = np.asarray(value)
    if arr.shape != tuple(shape):
        raise ValueError(f"Expected `{name}` to have shape {tuple(shape)}, got {arr.shape}.")
    if arr.dtype != np.bool_:
        if not (np.issubdtype(arr.dtype, np.integer) and np.isin(arr, (0, 1)).all()):
            raise TypeError(f"`{name}` must be a boolean mask, got dtype {arr.dtype}.")
        arr = arr.astype(bool)
    if not allow_empty and not arr.any():
        raise ValueError(f"`{name}` is empty (no pixel is set).")
    return arr


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole camera intrinsics (pixels) and image size.

    Parameters
    ----------
    fx, fy : float
        Focal lengths in pixels (> 0).
    cx, cy : float
        Principal point in pixels (column, row).
    width, height : int
        Image size in pixels (> 0).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not np.isfinite(value):
                raise ValueError(f"`{name}` must be finite, got {value}.")
            object.__setattr__(self, name, value)
        for name in ("fx", "fy"):
            if getattr(self, name) <= 0:
                raise ValueError(f"`{name}` must be positive, got {getattr(self, name)}.")
        for name in ("width", "height"):
            value = getattr(self, name)
            if int(value) != value or int(value) <= 0:
                raise ValueError(f"`{name}` must be a positive integer, got {value}.")
            object.__setattr__(self, name, int(value))

    @property
    def K(self) -> NDArray[np.float64]:
        """The 3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(height, width)``."""
        return (self.height, self.width)

    @classmethod
    def from_matrix(cls, K: ArrayLike, width: int, height: int) -> CameraIntrinsics:
        """Build from a 3x3 camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``."""
        K = as_float_array(K, "K")
        if K.shape != (3, 3):
            raise ValueError(f"Expected `K` to have shape (3, 3), got {K.shape}.")
        if not np.all(np.isfinite(K)):
            raise ValueError("`K` contains NaN or inf values.")
        if not np.allclose(K[2], [0.0, 0.0, 1.0]) or abs(K[1, 0]) > 1e-9:
            raise ValueError(f"`K` is not a pinhole camera matrix: {K.tolist()}.")
        if abs(K[0, 1]) > 1e-9:
            raise ValueError(f"`K` has a non-zero skew {K[0, 1]:g}; skew is not supported.")
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)

    def project(
        self, points: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Project camera-frame points.

        Parameters
        ----------
        points : array_like, shape (N, 3)
            Points in the camera frame, metres.

        Returns
        -------
        u, v : ndarray, shape (N,)
            Continuous image coordinates (column, row) in pixels; ``nan`` where ``z <= 0``.
        z : ndarray, shape (N,)
            Depth of each point in metres.
        """
        p = check_points(points, "points", min_points=0)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(z > 0, 1.0 / z, np.nan)
        return self.fx * p[:, 0] * inv + self.cx, self.fy * p[:, 1] * inv + self.cy, z

    def to_open3d(self) -> Any:
        """Return an ``open3d.camera.PinholeCameraIntrinsic``."""
        import open3d as o3d

        return o3d.camera.PinholeCameraIntrinsic(
            self.width, self.height, self.fx, self.fy, self.cx, self.cy
        )


def _check_depth(depth: Any, name: str, shape: tuple[int, int] | None) -> NDArray[np.float64]:
    arr = as_float_array(depth, name)
    if arr.ndim != 2:
        raise ValueError(f"Expected `{name}` to have shape (H, W), got {arr.shape}.")
    if shape is not None and arr.shape != tuple(shape):
        raise ValueError(f"Expected `{name}` to have shape {tuple(shape)}, got {arr.shape}.")
    if np.isnan(arr).any():
        raise ValueError(
            f"`{name}` contains {int(np.isnan(arr).sum())} NaN value(s); mark invalid depth with 0."
        )
    if np.isinf(arr).any():
        raise ValueError(f"`{name}` contains inf values; mark invalid depth with 0.")
    if (arr < 0).any():
        raise ValueError(f"`{name}` contains negative values (minimum {arr.min():g} m).")
    return arr


def backproject(
    depth: ArrayLike,
    intrinsics: CameraIntrinsics,
    *,
    mask: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Back-project the valid pixels of a depth image into camera-frame points.

    Parameters
    ----------
    depth : array_like, shape (H, W)
        Depth in metres along the optical axis; 0 marks invalid pixels.
    intrinsics : CameraIntrinsics
        Camera with ``(height, width) == depth.shape``.
    mask : array_like of bool, shape (H, W), optional
        Keep only these pixels (in addition to valid depth).

    Returns
    -------
    points : ndarray, shape (M, 3)
        Points in the camera frame (OpenCV: x right, y down, z forward), metres, in row-major
        pixel order.
    pixels : ndarray of int64, shape (M, 2)
        ``(row v, col u)`` of each point.

    Raises
    ------
    ValueError
        On shape mismatch, NaN/negative depth, an empty mask, or when no pixel is left.
    """
    d = _check_depth(depth, "depth", intrinsics.shape)
    valid = d > 0
    if mask is not None:
        valid &= check_mask(mask, "mask", intrinsics.shape)
    if not valid.any():
        where = " inside `mask`" if mask is not None else ""
        raise ValueError(f"`depth` has no valid (non-zero) pixel{where}; nothing to back-project.")
    v, u = np.nonzero(valid)
    z = d[v, u]
    points = np.empty((z.size, 3))
    points[:, 0] = (u - intrinsics.cx) * z / intrinsics.fx
    points[:, 1] = (v - intrinsics.cy) * z / intrinsics.fy
    points[:, 2] = z
    return points, np.stack([v, u], axis=1).astype(np.int64)


@dataclass(frozen=True, eq=False)
class RGBDFrame:
    """A posed RGB-D image.

    Parameters
    ----------
    color : ndarray of uint8, shape (H, W, 3), or None
        RGB image (``None`` for depth-only input).
    depth : ndarray, shape (H, W)
        Depth in metres (float64); 0 marks invalid pixels.
    intrinsics : CameraIntrinsics
        Camera with ``(height, width) == (H, W)``.
    T_world_camera : ndarray, shape (4, 4)
        Pose of the camera in the world (maps camera points into the world frame).
    mask : ndarray of bool, shape (H, W), or None
        Optional pixel mask (e.g. the object in an object view); must not be empty.
    """

    color: NDArray[np.uint8] | None
    depth: NDArray[np.float64]
    intrinsics: CameraIntrinsics
    T_world_camera: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    mask: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.intrinsics, CameraIntrinsics):
            raise TypeError(
                f"`intrinsics` must be a CameraIntrinsics, got {type(self.intrinsics).__name__}."
            )
        shape = self.intrinsics.shape
        depth = _check_depth(self.depth, "depth", None)
        if depth.shape != shape:
            raise ValueError(
                f"Expected `depth` to have shape {shape} (from the intrinsics), got {depth.shape}."
            )
        if not (depth > 0).any():
            raise ValueError("`depth` is zero everywhere: the frame has no valid measurement.")
        if depth.max() > MAX_DEPTH:
            raise ValueError(
                f"`depth` reaches {depth.max():g} m (> {MAX_DEPTH:g} m): it looks like raw sensor "
                "units; divide by the depth scale (e.g. 1000 for millimetres) to get metres."
            )
        depth.setflags(write=False)
        object.__setattr__(self, "depth", depth)
        if self.color is not None:
            color = np.asarray(self.color)
            if color.shape != (*shape, 3):
                raise ValueError(
                    f"Expected `color` to have shape {(*shape, 3)} to match `depth`, got {color.shape}."
                )
            if color.dtype != np.uint8:
                raise TypeError(f"`color` must have dtype uint8, got {color.dtype}.")
            color = color.copy()
            color.setflags(write=False)
            object.__setattr__(self, "color", color)
        T = check_transform(self.T_world_camera, "T_world_camera")
        T.setflags(write=False)
        object.__setattr__(self, "T_world_camera", T)
        if self.mask is not None:
            mask = check_mask(self.mask, "mask", shape).copy()
            mask.setflags(write=False)
            object.__setattr__(self, "mask", mask)

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(H, W)``."""
        return self.intrinsics.shape

    @property
    def T_camera_world(self) -> NDArray[np.float64]:
        """Inverse of ``T_world_camera``."""
        from solvers.lie import invert_transform

        return invert_transform(self.T_world_camera)

    def pixels_of(self, points: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.int64],
                                                     NDArray[np.float64], NDArray[np.bool_]]:
        """The nearest pixel of world points (N, 3), metres: ``(row, col, z, inside)``, with
        ``z`` the camera depth (metres) and ``inside`` whether the point lies in front of the
        camera and its pixel in the image (row and column are -1 where it is not in front)."""
        T = self.T_camera_world
        pc = check_points(points, "points", min_points=0) @ T[:3, :3].T + T[:3, 3]
        u, v, z = self.intrinsics.project(pc)
        ok = np.isfinite(u) & np.isfinite(v)
        col = np.full(u.shape, -1, dtype=np.int64)
        row = np.full(v.shape, -1, dtype=np.int64)
        col[ok] = np.floor(u[ok] + 0.5).astype(np.int64)
        row[ok] = np.floor(v[ok] + 0.5).astype(np.int64)
        h, w = self.shape
        ok &= (col >= 0) & (col < w) & (row >= 0) & (row < h)
        return row, col, z, ok

    def with_mask(self, mask: ArrayLike | None) -> RGBDFrame:
        """A copy of this frame with another mask."""
        return RGBDFrame(self.color, self.depth, self.intrinsics, self.T_world_camera, mask)

    def backproject(
        self, *, mask: ArrayLike | None | bool = True, world: bool = False
    ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """Back-project the valid pixels.

        Parameters
        ----------
        mask : array_like of bool, shape (H, W), or bool, optional
            ``True`` (default) uses the frame's own mask if any, ``False``/``None`` uses every
            pixel, an array uses that mask.
        world : bool, optional
            Return points in the world frame instead of the camera frame.

        Returns
        -------
        points : ndarray, shape (M, 3)
            Metres, camera (or world) frame.
        pixels : ndarray of int64, shape (M, 2)
            ``(row v, col u)``.
        """
        if mask is True:
            mask = self.mask
        elif mask is False:
            mask = None
        points, pixels = backproject(self.depth, self.intrinsics, mask=mask)
        if world:
            points = transform_points(self.T_world_camera, points)
        return points, pixels

    def colors_at(self, pixels: ArrayLike) -> NDArray[np.float64] | None:
        """Colours in ``[0, 1]`` (shape ``(M, 3)``) at ``(row, col)`` pixels, or ``None``."""
        if self.color is None:
            return None
        px = np.asarray(pixels)
        return self.color[px[:, 0], px[:, 1]].astype(np.float64) / 255.0


_INTRINSICS_KEYS = ("fx", "fy", "cx", "cy")


def _intrinsics_vector(intrinsics: Any) -> NDArray[np.float64]:
    """``(fx, fy, cx, cy)`` from a sequence or a mapping with those keys."""
    if isinstance(intrinsics, Mapping):
        missing = [k for k in _INTRINSICS_KEYS if k not in intrinsics]
        extra = sorted(str(k) for k in intrinsics if k not in _INTRINSICS_KEYS)
        if missing or extra:
            raise ValueError(
                "Expected `intrinsics` to have the keys fx, fy, cx, cy (pixels); "
                + (f"missing {', '.join(missing)}" if missing else "")
                + ("; " if missing and extra else "")
                + (f"unknown {', '.join(extra)}" if extra else "") + ".")
        intrinsics = [intrinsics[k] for k in _INTRINSICS_KEYS]
    k = as_float_array(intrinsics, "intrinsics", allow_bool=False).reshape(-1)
    if k.shape != (4,):
        raise ValueError(f"Expected `intrinsics` to be (fx, fy, cx, cy) in pixels, got "
                         f"{k.size} value(s).")
    return k


def load_rgbd(
    color_path: str | Path | None,
    depth_path: str | Path,
    intrinsics: CameraIntrinsics | ArrayLike,
    *,
    depth_scale: float = 1000.0,
    T_world_camera: ArrayLike | None = None,
    mask: ArrayLike | None = None,
) -> RGBDFrame:
    """Read an RGB-D frame from image files.

    Parameters
    ----------
    color_path : path or None
        8-bit RGB image (an alpha channel is dropped, grey is replicated).
    depth_path : path
        Single-channel depth image; metres = value / ``depth_scale``.
    intrinsics : CameraIntrinsics, (4,) array_like or mapping
        Or ``(fx, fy, cx, cy)`` in pixels (a sequence, or a mapping with exactly those keys),
        the image size then the depth image's.
    depth_scale : float, optional
        Raw depth units per metre (1000 for millimetre PNGs; YCB-Video uses 10000).
    T_world_camera : array_like, shape (4, 4), optional
    mask : array_like of bool, shape (H, W), optional

    Raises
    ------
    ValueError
        Malformed intrinsics, or intrinsics implausible for the image size
        (:func:`certpose.geometry.plausibility.check_intrinsics`).
    """
    if not depth_scale > 0:
        raise ValueError(f"`depth_scale` must be positive, got {depth_scale}.")
    raw = read_image(depth_path, "depth")
    if raw.ndim != 2:
        raise ValueError(f"Expected the depth image {depth_path} to have one channel, got shape {raw.shape}.")
    if not isinstance(intrinsics, CameraIntrinsics):
        k = _intrinsics_vector(intrinsics)
        intrinsics = CameraIntrinsics(*(float(v) for v in k), raw.shape[1], raw.shape[0])
    from certpose.geometry.plausibility import check_intrinsics

    check_intrinsics(intrinsics)
    color = None
    if color_path is not None:
        color = read_image(color_path, "color")
        if color.ndim == 2:
            color = np.repeat(color[..., None], 3, axis=2)
        color = np.ascontiguousarray(color[..., :3]).astype(np.uint8)
    return RGBDFrame(
        color,
        raw.astype(np.float64) / depth_scale,
        intrinsics,
        np.eye(4) if T_world_camera is None else T_world_camera,
        mask,
    )


#: PNG modes that Pillow decodes to the very array imageio returns (imageio converts the others:
#: palettes to colours, 32-bit "I" to 16 bits).
_PLAIN_PNG_MODES = frozenset({"L", "LA", "RGB", "RGBA", "I;16"})


def read_mask(path: str | Path, shape: tuple[int, int]) -> NDArray[np.bool_]:
    """Read an object mask image: non-zero pixels (any channel) are the object's.

    Parameters
    ----------
    path : path
    shape : (H, W)
        The frame's image size, which the mask must have.

    Raises
    ------
    FileNotFoundError, OSError
        A missing or unreadable file.
    ValueError
        Another size, or no object pixel.
    """
    raw = read_image(path, "mask")
    if raw.shape[:2] != tuple(shape):
        raise ValueError(f"The mask {path} is {raw.shape[1]}x{raw.shape[0]} pixels, the depth image "
                         f"{shape[1]}x{shape[0]}.")
    mask = (raw if raw.ndim == 2 else raw[..., :3].max(axis=2)) != 0
    if not mask.any():
        raise ValueError(f"The mask {path} has no object pixel (all zero).")
    return mask


def read_image(path: str | Path, what: str = "image") -> NDArray[Any]:
    """Read an image file into an array, as ``imageio.v3.imread`` does.

    Single-frame PNGs in the modes imageio leaves as they are (8-bit grey or colour, 16-bit grey:
    YCB-Video's colour, depth and label images) are decoded by Pillow directly, which spares a
    ``certpose pose`` run imageio's import (~0.02 s) and its plugin look-up (~0.02 s for the
    three images of a frame); every other file goes through imageio.

    Parameters
    ----------
    path : path
    what : str, optional
        What the image is, for the error messages ("depth", "color", ...).

    Returns
    -------
    ndarray
        Shape (H, W) or (H, W, C), the file's dtype (uint8, uint16, ...); writeable.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    OSError
        The file cannot be read as an image.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"The {what} image {path} does not exist.")
    if path.suffix.lower() == ".png":
        with path.open("rb") as fh:
            head = fh.read(8)
        if head != b"\x89PNG\r\n\x1a\n":  # not worth every imageio plugin's attempt
            raise OSError(f"Cannot read the {what} image {path}: not a PNG file (it starts "
                          f"with {head!r}; a PNG starts with b'\\x89PNG').")
        from PIL import Image  # imageio's own PNG reader (a dependency of imageio)

        try:
            with Image.open(path, formats=("PNG",)) as im:
                if im.mode in _PLAIN_PNG_MODES and getattr(im, "n_frames", 1) == 1:
                    return np.array(im)
        except Exception:  # imageio reads it or says why not
            pass
    import imageio.v3 as iio

    try:
        return np.asarray(iio.imread(path))
    except Exception as exc:
        # imageio's "no backend" advice (install a plugin) is wrong for a file that is not an
        # image at all: say what the file is not.
        text = str(exc)
        if "Could not find a backend" in text or "cannot identify image file" in text:
            text = (f"not an image file imageio can read (it starts with "
                    f"{path.read_bytes()[:8]!r}; a PNG starts with b'\\x89PNG')")
        raise OSError(f"Cannot read the {what} image {path}: {text}") from exc


@dataclass(frozen=True, eq=False)
class StructuredPointCloud:
    """Points with a descriptor (and optionally a colour) each.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Coordinates in metres (N >= 1).
    descriptors : ndarray, shape (N, d)
        Per-point descriptors (float64; ``d`` may be 0). Backbones produce L2-normalised rows.
    colors : ndarray, shape (N, 3), optional
        RGB in ``[0, 1]``.
    """

    points: NDArray[np.float64]
    descriptors: NDArray[np.float64]
    colors: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        points = check_points(self.points, "points")
        n = points.shape[0]
        # A container: any finite descriptors, also none (d = 0); eq. (1)'s users check norms.
        desc = check_descriptors(self.descriptors, "descriptors", n, unit_norm=False, min_dim=0)
        for arr in (points, desc):
            arr.setflags(write=False)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "descriptors", desc)
        if self.colors is not None:
            colors = as_float_array(self.colors, "colors")
            if colors.shape != (n, 3):
                raise ValueError(f"Expected `colors` to have shape ({n}, 3), got {colors.shape}.")
            if not np.all(np.isfinite(colors)) or colors.min() < 0 or colors.max() > 1:
                raise ValueError("`colors` must be finite and within [0, 1].")
            colors.setflags(write=False)
            object.__setattr__(self, "colors", colors)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def dim(self) -> int:
        """Descriptor dimension ``d``."""
        return int(self.descriptors.shape[1])

    def voxel_downsample(self, voxel_size: float) -> StructuredPointCloud:
        """Average the points falling into each cubic voxel of side ``voxel_size`` (metres).

        Each occupied voxel (cells ``floor(p / voxel_size)``) gives one point: the mean point,
        the mean descriptor re-L2-normalised (a zero mean stays zero), and the mean colour.
        Output order: lexicographic voxel index.
        """
        if not (np.isfinite(voxel_size) and voxel_size > 0):
            raise ValueError(f"`voxel_size` must be positive and finite, got {voxel_size}.")
        keys = np.floor(self.points / voxel_size).astype(np.int64)
        _, inverse, counts = group_voxels(keys)
        m = counts.size

        def mean(values: NDArray[np.float64]) -> NDArray[np.float64]:
            return sum_by_group(inverse, values, m) / counts[:, None]

        return StructuredPointCloud(
            mean(self.points),
            normalize_rows(mean(self.descriptors)) if self.dim else np.zeros((m, 0)),
            None if self.colors is None else np.clip(mean(self.colors), 0.0, 1.0),
        )

    def transform(self, T: ArrayLike) -> StructuredPointCloud:
        """Apply a rigid transform ``T`` (4x4) to the points; descriptors are unchanged."""
        T = check_transform(T, "T")
        return StructuredPointCloud(transform_points(T, self.points), self.descriptors, self.colors)

    def select(self, index: ArrayLike) -> StructuredPointCloud:
        """The sub-cloud of the given indices or boolean mask."""
        idx = np.asarray(index)
        return StructuredPointCloud(
            self.points[idx], self.descriptors[idx], None if self.colors is None else self.colors[idx]
        )

    def to_open3d(self) -> o3d.geometry.PointCloud:
        """An ``open3d.geometry.PointCloud`` with the points (and colours); descriptors are dropped."""
        import open3d as o3d

        # open3d refuses read-only buffers: hand it copies.
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(self.points)))
        if self.colors is not None:
            pcd.colors = o3d.utility.Vector3dVector(np.array(self.colors))
        return pcd

    @classmethod
    def from_open3d(
        cls, pcd: o3d.geometry.PointCloud, descriptors: ArrayLike | None = None
    ) -> StructuredPointCloud:
        """Wrap an open3d point cloud; without ``descriptors`` the descriptor dimension is 0."""
        points = np.asarray(pcd.points, dtype=np.float64)
        colors = np.asarray(pcd.colors, dtype=np.float64) if pcd.has_colors() else None
        if descriptors is None:
            descriptors = np.zeros((points.shape[0], 0))
        return cls(points, descriptors, colors)
