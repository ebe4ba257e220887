"""Feature backbones: per-point (or per-pixel) descriptors, L2-normalised.

Every backbone returns rows of unit length (or zero, for points it cannot describe), so the
inner product of two descriptors is a similarity in ``[-1, 1]``, as eq. (1) of the paper assumes.

* :class:`FPFHBackbone` (offline default): open3d's FPFH geometric descriptor (computed by
  :mod:`certpose.geometry._fpfh_kernels`, open3d's numbers without its import), optionally joined
  with colour.
* :class:`ArrayBackbone`: descriptors the user already has (per point or per pixel).
* :class:`DinoBackbone`: a DINO vision transformer loaded from a local TorchScript file (optional
  extra; needs torch, never downloads).

:func:`describe_frame` turns a (masked) RGB-D frame into a :class:`~certpose.geometry.rgbd.StructuredPointCloud`
with any backbone.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from certpose.geometry.rgbd import (
    RGBDFrame,
    StructuredPointCloud,
    check_descriptors,
    normalize_rows,
)
from solvers.lie import transform_points
from solvers.validation import as_float_array, check_points

__all__ = [
    "FeatureBackbone",
    "FPFHBackbone",
    "ArrayBackbone",
    "DinoBackbone",
    "describe_frame",
    "resolve_backbone",
]

log = logging.getLogger(__name__)


@runtime_checkable
class FeatureBackbone(Protocol):
    """Anything that describes points: ``describe(points, *, colors=None, normals=None)``.

    Implementations return an ``(N, d)`` float64 array of L2-normalised rows. A backbone that
    works on images may also define ``describe_image(color) -> (H, W, d)``; :func:`describe_frame`
    prefers it when present.
    """

    @property
    def dim(self) -> int:  # pragma: no cover - protocol
        """Descriptor dimension ``d``."""
        ...

    def describe(
        self,
        points: NDArray[np.float64],
        *,
        colors: NDArray[np.float64] | None = None,
        normals: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:  # pragma: no cover - protocol
        """Descriptors of ``points`` (N, 3), shape (N, d), rows L2-normalised."""
        ...


_FPFH_KERNELS = "certpose.geometry._fpfh_kernels"

# Sub-histograms of open3d's 33-bin FPFH (three angle features, 11 bins each).
_FPFH_BLOCKS = 3
_FPFH_BINS = 11


@dataclass(frozen=True)
class FPFHBackbone:
    """FPFH (open3d) geometric descriptors, optionally joined with colour.

    Descriptor construction, per point:

    1. open3d's 33-bin FPFH (three 11-bin angle histograms) with neighbours within ``radius``
       (at most ``max_nn``), on normals estimated within ``normal_radius`` and oriented towards
       ``viewpoint`` (or given by the caller);
    2. each 11-bin histogram is normalised to sum 1 and square-rooted (Hellinger map);
    3. *centring*: FPFH bins are non-negative, so raw histograms of unrelated points still have
       large positive inner products (about 0.7 on YCB-Video). With ``center`` set (a fixed
       33-vector, normally the mean square-rooted histogram of the scene, see
       :meth:`fit_center`; ``build_scene_field(..., fit_backbone=True)`` fits it and returns the
       fitted backbone as ``SceneField.backbone``), that vector is subtracted:
       unrelated points then have inner products near 0 (measured -0.06 +- 0.5 on YCB-Video
       frame 0000/000001) while matching points keep a positive one. Without ``center``, each
       histogram's own mean bin value is subtracted (data-independent but weaker: the common
       shape of all histograms remains). Object and scene must use the *same* backbone;
    4. with ``color_weight = w > 0`` and colours given, the unit geometric part is scaled by
       ``sqrt(1 - w)`` and joined with ``sqrt(w) * (2 c - 1) / sqrt(3)`` (centred RGB), then the
       row is L2-normalised again; without colours the colour block is zero.

    Parameters
    ----------
    radius : float, optional
        FPFH support radius in metres (default 0.025).
    max_nn : int, optional
        Maximum neighbours for FPFH (default 40; the cost grows with it).
    normal_radius : float, optional
        Normal estimation radius (default ``radius / 2``).
    color_weight : float, optional
        Share of the colour block in ``[0, 1)`` (default 0: geometry only).
    viewpoint : array_like, shape (3,), or None
        Estimated normals are flipped towards this point (the camera centre when the points are
        in the camera frame: default the origin). ``None`` orients them consistently along a
        tangent-plane graph, pointing away from the centroid on the whole (for model clouds
        that have no camera).
    center : array_like, shape (33,), or None
        Reference square-rooted histogram subtracted before normalisation (see above).
    """

    radius: float = 0.025
    max_nn: int = 40
    normal_radius: float | None = None
    color_weight: float = 0.0
    viewpoint: tuple[float, float, float] | None = (0.0, 0.0, 0.0)
    center: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"`radius` must be positive, got {self.radius}.")
        if int(self.max_nn) != self.max_nn or self.max_nn < 2:
            raise ValueError(f"`max_nn` must be an integer >= 2, got {self.max_nn}.")
        if self.normal_radius is not None and not self.normal_radius > 0:
            raise ValueError(f"`normal_radius` must be positive, got {self.normal_radius}.")
        if not 0.0 <= self.color_weight < 1.0:
            raise ValueError(f"`color_weight` must be in [0, 1), got {self.color_weight}.")
        if self.viewpoint is not None:
            vp = np.asarray(self.viewpoint, dtype=np.float64)
            if vp.shape != (3,) or not np.all(np.isfinite(vp)):
                raise ValueError(f"Expected `viewpoint` to have shape (3,), got {vp.shape}.")
            object.__setattr__(self, "viewpoint", tuple(float(x) for x in vp))
        if self.center is not None:
            c = np.asarray(self.center, dtype=np.float64)
            n_bins = _FPFH_BLOCKS * _FPFH_BINS
            if c.shape != (n_bins,) or not np.all(np.isfinite(c)):
                raise ValueError(f"Expected `center` to have shape ({n_bins},), got {c.shape}.")
            object.__setattr__(self, "center", tuple(float(x) for x in c))

    @property
    def dim(self) -> int:
        """Descriptor dimension: 33, plus 3 with colour."""
        return _FPFH_BLOCKS * _FPFH_BINS + (3 if self.color_weight > 0 else 0)

    def histograms(self, points: ArrayLike, *, normals: ArrayLike | None = None,
                   rows: ArrayLike | None = None) -> NDArray[np.float64]:
        """Square-rooted, normalised FPFH histograms, shape ``(N, 33)`` (steps 1-2 above).

        ``rows`` (indices into ``points``): only those points' histograms, shape
        ``(len(rows), 33)``, still over all the points' neighbourhoods (the same values as the
        full result's rows; the cost of the skipped rows' final step is saved).

        Normals oriented towards ``viewpoint`` and the FPFH are computed by
        :mod:`certpose.geometry._fpfh_kernels` (open3d's computation, without its import);
        ``viewpoint=None`` orients the normals with open3d's tangent-plane graph. While a
        first run's warm-up compiles those kernels (:func:`solvers.jit.warm_up`), open3d
        computes the same numbers instead.
        """
        from solvers.jit import pending

        p = np.ascontiguousarray(check_points(points, "points", min_points=5), dtype=np.float64)
        n = p.shape[0]
        sel = np.arange(n, dtype=np.int64) if rows is None else np.asarray(rows, dtype=np.int64).reshape(-1)
        if sel.size and (sel.min() < 0 or sel.max() >= n):
            raise ValueError(f"`rows` must index the {n} points, got values in [{sel.min()}, {sel.max()}].")
        nr = self.normal_radius if self.normal_radius is not None else self.radius / 2
        if _FPFH_KERNELS in pending():
            # A first run: a warm-up helper is compiling the kernels (seconds, once); open3d
            # computes the same numbers meanwhile.
            h = self._open3d_fpfh(p, normals, nr)[sel]
        else:
            h = self._kernel_fpfh(p, normals, nr, sel)
        h = h.reshape(sel.size, _FPFH_BLOCKS, _FPFH_BINS)
        total = h.sum(axis=2, keepdims=True)
        # Isolated points get an all-zero histogram: they stay zero (similar to nothing).
        h = np.sqrt(np.divide(h, total, out=np.zeros_like(h), where=total > 0))
        return h.reshape(sel.size, -1)

    def _kernel_fpfh(self, p: NDArray[np.float64], normals: ArrayLike | None, nr: float,
                     sel: NDArray[np.int64]) -> NDArray[np.float64]:
        """Raw FPFH (len(sel), 33) by :mod:`certpose.geometry._fpfh_kernels`."""
        from solvers.jit import compiled

        kernels = compiled(_FPFH_KERNELS)
        if normals is not None:
            nm = check_points(normals, "normals")
            if nm.shape != p.shape:
                raise ValueError(f"Expected `normals` to have shape {p.shape}, got {nm.shape}.")
            nm = normalize_rows(nm)
        elif self.viewpoint is not None:
            # Neighbour grid cells of the normals' radius (the FPFH's reaches two cells).
            nm = kernels.normals_towards(p, float(nr), 30, float(nr),
                                         np.asarray(self.viewpoint, dtype=np.float64))
        else:
            nm = self._consistent_normals(p, nr)
        return kernels.fpfh(p, np.ascontiguousarray(nm, dtype=np.float64), float(self.radius),
                            int(self.max_nn), float(nr), np.ascontiguousarray(sel))

    def _open3d_fpfh(self, p: NDArray[np.float64], normals: ArrayLike | None,
                     nr: float) -> NDArray[np.float64]:
        """Raw FPFH (N, 33) by open3d (the kernels' numbers, while they compile)."""
        import open3d as o3d

        if normals is not None:
            nm = check_points(normals, "normals")
            if nm.shape != p.shape:
                raise ValueError(f"Expected `normals` to have shape {p.shape}, got {nm.shape}.")
            nm = normalize_rows(nm)
        elif self.viewpoint is None:
            nm = self._consistent_normals(p, nr)
        else:
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
            pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=nr, max_nn=30))
            pcd.orient_normals_towards_camera_location(np.asarray(self.viewpoint))
            nm = np.asarray(pcd.normals)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
        pcd.normals = o3d.utility.Vector3dVector(np.array(nm))
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=self.radius, max_nn=int(self.max_nn)))
        return np.array(np.asarray(fpfh.data).T)

    @staticmethod
    def _consistent_normals(p: NDArray[np.float64], radius: float) -> NDArray[np.float64]:
        """open3d's normals oriented along its tangent-plane graph, pointing away from the
        centroid on the whole (model clouds without a camera)."""
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
        pcd.orient_normals_consistent_tangent_plane(10)
        nm = np.asarray(pcd.normals)
        # The propagation fixes the orientation up to one global sign: point outwards.
        if np.sum(nm * (p - p.mean(axis=0))) < 0:
            nm = -nm
        return np.array(nm)

    def fit_center(self, histograms: ArrayLike) -> FPFHBackbone:
        """A copy whose ``center`` is the mean of ``histograms`` (from :meth:`histograms`)."""
        h = check_descriptors(histograms, "histograms", unit_norm=False)
        if h.shape[1] != _FPFH_BLOCKS * _FPFH_BINS or h.shape[0] == 0:
            raise ValueError(f"Expected `histograms` to have shape (N, 33) with N >= 1, got {h.shape}.")
        valid = h.any(axis=1)
        mean = h[valid].mean(axis=0) if valid.any() else np.zeros(h.shape[1])
        return replace(self, center=tuple(float(x) for x in mean))

    def finish(self, histograms: ArrayLike, *, colors: ArrayLike | None = None) -> NDArray[np.float64]:
        """Descriptors from :meth:`histograms` output (steps 3-4 above), shape ``(N, dim)``."""
        h = check_descriptors(histograms, "histograms", unit_norm=False)
        n = h.shape[0]
        empty = ~h.any(axis=1)
        if self.center is None:
            h = (h.reshape(n, _FPFH_BLOCKS, _FPFH_BINS) - h.reshape(n, _FPFH_BLOCKS, _FPFH_BINS).mean(
                axis=2, keepdims=True
            )).reshape(n, -1)
        else:
            h = h - np.asarray(self.center)
        h[empty] = 0.0
        geo = normalize_rows(h)
        if self.color_weight <= 0:
            return geo
        block = np.zeros((n, 3))
        if colors is not None:
            c = as_float_array(colors, "colors")
            if c.shape != (n, 3):
                raise ValueError(f"Expected `colors` to have shape ({n}, 3), got {c.shape}.")
            if not np.all(np.isfinite(c)):
                raise ValueError("`colors` contains NaN or inf values.")
            block = (2.0 * np.clip(c, 0.0, 1.0) - 1.0) / np.sqrt(3.0)
        w = self.color_weight
        return normalize_rows(np.hstack([np.sqrt(1.0 - w) * geo, np.sqrt(w) * block]))

    def describe(
        self,
        points: ArrayLike,
        *,
        colors: ArrayLike | None = None,
        normals: ArrayLike | None = None,
        rows: ArrayLike | None = None,
    ) -> NDArray[np.float64]:
        """FPFH(+colour) descriptors, shape ``(N, dim)``, rows L2-normalised.

        Parameters
        ----------
        points : array_like, shape (N, 3)
            Metres; at least 5 points.
        colors : array_like, shape (N, 3), optional
            RGB in ``[0, 1]``; used when ``color_weight > 0``.
        normals : array_like, shape (N, 3), optional
            Normals; estimated when omitted.
        rows : array_like of int, optional
            Describe only these points (shape ``(len(rows), dim)``; ``colors`` stays (N, 3)),
            over all the points' neighbourhoods (see :meth:`histograms`).
        """
        h = self.histograms(points, normals=normals, rows=rows)
        if colors is not None and rows is not None:
            colors = np.asarray(colors)[np.asarray(rows, dtype=np.int64).reshape(-1)]
        return self.finish(h, colors=colors)


class ArrayBackbone:
    """User-supplied descriptors, per point ``(N, d)`` or per pixel ``(H, W, d)``.

    ``describe(points)`` returns the per-point array (its row count must match ``points``);
    ``describe_image(color)`` returns the per-pixel array (its size must match the image).
    Rows are L2-normalised unless ``normalize=False``; NaN or inf raises ``ValueError``.
    """

    def __init__(self, descriptors: ArrayLike, *, normalize: bool = True) -> None:
        arr = as_float_array(descriptors, "descriptors")
        if arr.ndim not in (2, 3):
            raise ValueError(
                f"Expected `descriptors` to have shape (N, d) or (H, W, d), got {arr.shape}."
            )
        if not np.all(np.isfinite(arr)):
            bad = int(np.count_nonzero(~np.isfinite(arr).all(axis=-1)))
            raise ValueError(f"`descriptors` contains NaN or inf values in {bad} row(s).")
        if normalize:
            arr = normalize_rows(arr)
        arr.setflags(write=False)
        self._descriptors = arr

    @property
    def dim(self) -> int:
        return int(self._descriptors.shape[-1])

    @property
    def per_pixel(self) -> bool:
        """Whether the descriptors are an ``(H, W, d)`` image."""
        return self._descriptors.ndim == 3

    def describe(
        self,
        points: ArrayLike,
        *,
        colors: ArrayLike | None = None,
        normals: ArrayLike | None = None,
    ) -> NDArray[np.float64]:
        if self.per_pixel:
            raise ValueError(
                "These descriptors are per pixel (H, W, d); use them through describe_frame or "
                "build_scene_field, which index them by pixel."
            )
        p = check_points(points, "points", min_points=0)
        if p.shape[0] != self._descriptors.shape[0]:
            raise ValueError(
                f"Expected {self._descriptors.shape[0]} points to match `descriptors`, got {p.shape[0]}."
            )
        return self._descriptors

    def describe_image(self, color: NDArray[np.uint8] | None, shape: tuple[int, int] | None = None) -> NDArray[np.float64]:
        """The per-pixel descriptors, shape ``(H, W, d)`` (checked against the image size)."""
        if not self.per_pixel:
            raise ValueError("These descriptors are per point (N, d), not an (H, W, d) image.")
        size = shape if shape is not None else (None if color is None else color.shape[:2])
        if size is not None and self._descriptors.shape[:2] != tuple(size):
            raise ValueError(
                f"Expected `descriptors` to have shape {(*size, self.dim)} to match the image, "
                f"got {self._descriptors.shape}."
            )
        return self._descriptors


class DinoBackbone:
    """DINO ViT features from a local TorchScript file (optional extra; needs torch).

    The file must hold a module mapping a normalised image batch ``(1, 3, H', W')`` (``H'``,
    ``W'`` multiples of ``patch_size``) to patch tokens ``(1, h*w [+1 class token], d)`` or a
    feature map ``(1, d, h, w)``. Tokens are bilinearly upsampled to the full image, as in the
    paper's appendix, and L2-normalised per pixel. Nothing is downloaded.

    Parameters
    ----------
    weights_path : path
        The TorchScript file (``torch.jit.save`` of the model).
    patch_size : int, optional
        ViT patch size (14 for DINOv2, 8 or 16 for DINO).
    input_size : int, optional
        Shorter image side fed to the network (rounded to the patch size).
    device : str, optional
    """

    def __init__(
        self,
        weights_path: str | Path,
        *,
        patch_size: int = 14,
        input_size: int = 448,
        device: str = "cpu",
    ) -> None:
        path = Path(weights_path)
        if not path.is_file():
            raise FileNotFoundError(f"The DINO weights file {path} does not exist.")
        try:
            import torch
        except ImportError as exc:
            raise ImportError(
                "DinoBackbone needs PyTorch, which is not installed; install torch (CPU build is "
                "enough) or use FPFHBackbone / ArrayBackbone."
            ) from exc
        self._torch = torch
        self._model = torch.jit.load(str(path), map_location=device).eval()
        self._device = device
        self.patch_size = int(patch_size)
        self.input_size = int(input_size)
        self._dim: int | None = None

    @property
    def dim(self) -> int:
        """Descriptor dimension (0 until the first image has been described)."""
        return 0 if self._dim is None else self._dim

    def describe(self, points: ArrayLike, *, colors: Any = None, normals: Any = None) -> NDArray[np.float64]:
        """Not available: DINO needs the image (use :func:`describe_frame`)."""
        raise ValueError("DinoBackbone describes images, not bare points; use describe_frame.")

    def describe_image(self, color: NDArray[np.uint8] | None, shape: tuple[int, int] | None = None) -> NDArray[np.float64]:
        """Per-pixel descriptors ``(H, W, d)`` of an RGB uint8 image."""
        if color is None:
            raise ValueError("DinoBackbone needs a colour image; the frame has none.")
        torch = self._torch
        F = torch.nn.functional
        h, w = color.shape[:2]
        scale = self.input_size / min(h, w)
        hp = max(self.patch_size, int(round(h * scale / self.patch_size)) * self.patch_size)
        wp = max(self.patch_size, int(round(w * scale / self.patch_size)) * self.patch_size)
        x = torch.from_numpy(np.ascontiguousarray(color)).permute(2, 0, 1)[None].float() / 255.0
        x = F.interpolate(x, size=(hp, wp), mode="bilinear", align_corners=False)
        mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
        std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
        with torch.no_grad():
            out = self._model(((x - mean) / std).to(self._device))
            gh, gw = hp // self.patch_size, wp // self.patch_size
            if out.ndim == 2:
                raise ValueError(
                    f"The DINO model returned global features of shape {tuple(out.shape)}; export a "
                    "module that returns the patch tokens (1, h*w[+1], d) or a map (1, d, h, w)."
                )
            if out.ndim == 3:
                out = out[:, -gh * gw :, :].reshape(1, gh, gw, -1).permute(0, 3, 1, 2)
            feat = F.interpolate(out.float(), size=(h, w), mode="bilinear", align_corners=False)
        arr = feat[0].permute(1, 2, 0).cpu().numpy().astype(np.float64)
        self._dim = int(arr.shape[-1])
        return normalize_rows(arr)


def resolve_backbone(backbone_or_descriptors: Any) -> Any:
    """A backbone from a backbone, ``None`` (default :class:`FPFHBackbone`) or an array."""
    if backbone_or_descriptors is None:
        return FPFHBackbone()
    if isinstance(backbone_or_descriptors, np.ndarray) or isinstance(
        backbone_or_descriptors, (list, tuple)
    ):
        return ArrayBackbone(backbone_or_descriptors)
    if not hasattr(backbone_or_descriptors, "describe"):
        raise TypeError(
            "Expected a feature backbone (with a `describe` method) or a descriptor array, got "
            f"{type(backbone_or_descriptors).__name__}."
        )
    return backbone_or_descriptors


def describe_frame(
    frame: RGBDFrame,
    backbone: Any = None,
    *,
    mask: ArrayLike | None | bool = True,
    voxel_size: float | None = None,
    world: bool = True,
) -> StructuredPointCloud:
    """A structured point cloud of a frame's (masked) pixels.

    Image backbones (with ``describe_image``, e.g. per-pixel arrays or DINO) give each pixel its
    descriptor; point backbones (FPFH) describe the camera-frame points, after averaging them per
    voxel when ``voxel_size`` is given (so the descriptor density matches a scene field of the
    same voxel size). With an image backbone and ``voxel_size``, points and descriptors are
    averaged per voxel afterwards.

    Parameters
    ----------
    frame : RGBDFrame
    backbone : FeatureBackbone, array or None
        ``None`` uses the default :class:`FPFHBackbone`.
    mask : array_like of bool, shape (H, W), or bool, optional
        ``True`` (default) uses ``frame.mask``; ``False``/``None`` all pixels.
    voxel_size : float, optional
        Voxel side in metres for downsampling.
    world : bool, optional
        Express the result in the world frame (``frame.T_world_camera``), else the camera frame.
    """
    backbone = resolve_backbone(backbone)
    if isinstance(backbone, FPFHBackbone) and backbone.viewpoint != (0.0, 0.0, 0.0):
        # The points are described in the camera frame: orient normals towards the camera.
        backbone = replace(backbone, viewpoint=(0.0, 0.0, 0.0))
    points, pixels = frame.backproject(mask=mask, world=False)
    colors = frame.colors_at(pixels)
    if hasattr(backbone, "describe_image") and getattr(backbone, "per_pixel", True):
        image = backbone.describe_image(frame.color, frame.shape)
        cloud = StructuredPointCloud(points, image[pixels[:, 0], pixels[:, 1]], colors)
        if voxel_size is not None:
            cloud = cloud.voxel_downsample(voxel_size)
    else:
        if voxel_size is not None:
            cloud = StructuredPointCloud(points, np.zeros((len(points), 0)), colors)
            cloud = cloud.voxel_downsample(voxel_size)
            points, colors = cloud.points, cloud.colors
        desc = check_descriptors(
            backbone.describe(points, colors=colors), "descriptors", len(points)
        )
        cloud = StructuredPointCloud(points, desc, colors)
    if world:
        cloud = StructuredPointCloud(
            transform_points(frame.T_world_camera, cloud.points), cloud.descriptors, cloud.colors
        )
    return cloud
