"""Reader and writer of datasets in the BOP layout (the BOP toolkit's format).

A dataset folder holds ``models/`` (``obj_{obj_id:06d}.ply`` in millimetres and
``models_info.json``: ``diameter``, ``min_x/y/z``, ``size_x/y/z`` in millimetres and the
symmetries ``symmetries_discrete`` (4x4 row-major, millimetres) and ``symmetries_continuous``
(``axis``, ``offset`` in millimetres)), one folder per split (``test/``) with one folder per
scene (``{scene_id:06d}/``: ``rgb/``, ``depth/``, ``mask_visib/``, ``scene_camera.json``,
``scene_gt.json``, ``scene_gt_info.json``) and target lists such as ``test_targets_bop19.json``.
Depth in millimetres is the depth image times ``depth_scale`` (``scene_camera.json``); poses
``cam_R_m2c``, ``cam_t_m2c`` map model points into the camera frame (millimetres).

Units are converted here, once: everything this module returns is in metres
(``T_camera_object`` 4x4, model points, diameters, symmetries); everything it writes is in
millimetres.
"""

from __future__ import annotations

import json
import logging
import math
import os
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "BOPDataset",
    "BOPObject",
    "BOPTarget",
    "BOPInstance",
    "MM",
    "load_bop_targets",
    "read_bop_ply",
    "write_bop_ply",
    "write_bop_json",
    "symmetry_transforms",
    "group_targets",
    "open_dataset",
]

log = logging.getLogger(__name__)

MM = 1000.0
"""Millimetres per metre: BOP's files are in millimetres, certpose works in metres."""


@dataclass(frozen=True)
class BOPTarget:
    """One estimation target: ``inst_count`` instances of object ``obj_id`` in an image."""

    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int = 1


@dataclass(frozen=True, eq=False)
class BOPInstance:
    """One annotated object instance of an image (``scene_gt.json`` + ``scene_gt_info.json``).

    Attributes
    ----------
    gt_id : int
        Index of the instance in the image's list (the suffix of its mask's file name).
    obj_id : int
    T_camera_object : ndarray, shape (4, 4)
        Maps model points into the camera frame, metres.
    visib_fract : float or None
        Visible fraction of the object's silhouette (``scene_gt_info.json``).
    """

    gt_id: int
    obj_id: int
    T_camera_object: NDArray[np.float64] = field(repr=False)
    visib_fract: float | None = None


@dataclass(frozen=True, eq=False)
class BOPObject:
    """An object model of a BOP dataset, in metres.

    Attributes
    ----------
    obj_id : int
    points : ndarray, shape (N, 3)
        The model's vertices, object frame, metres (rounded to the nanometre).
    faces : ndarray of int, shape (M, 3) or None
        Triangles (``None`` for a point-cloud model).
    diameter : float
        Largest distance between two vertices, metres (``models_info.json``).
    symmetries : ndarray, shape (K, 4, 4)
        The symmetry transformations in the BOP toolkit's sense (identity first, continuous
        symmetries discretised, see :func:`symmetry_transforms`), metres.
    info : dict
        The raw ``models_info.json`` entry (millimetres).
    """

    obj_id: int
    points: NDArray[np.float64] = field(repr=False)
    faces: NDArray[np.int64] | None = field(repr=False)
    diameter: float
    symmetries: NDArray[np.float64] = field(repr=False)
    info: dict[str, Any] = field(repr=False)

    @property
    def name(self) -> str:
        return f"obj_{self.obj_id:06d}"


def _json(path: Path) -> Any:
    if not path.is_file():
        raise FileNotFoundError(f"The BOP file {path} does not exist.")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path} is not valid JSON ({exc}).") from None


def _int_keys(d: Any, path: Path) -> dict[int, Any]:
    if not isinstance(d, dict):
        raise ValueError(f"Expected {path} to hold an object keyed by id, got {type(d).__name__}.")
    try:
        return {int(k): v for k, v in d.items()}
    except ValueError:
        raise ValueError(f"{path}: keys must be integer ids, got {list(d)[:3]}.") from None


def write_bop_json(path: str | os.PathLike[str], content: Any) -> Path:
    """Write ``content`` as JSON (sorted integer keys written as strings), atomically."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=p.parent, suffix=".tmp")
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        json.dump(content, fh, indent=1, sort_keys=False)
        fh.write("\n")
    os.replace(tmp, p)
    return p


def read_bop_ply(path: str | os.PathLike[str]) -> tuple[NDArray[np.float64], NDArray[np.int64] | None]:
    """Vertices (N, 3) in the file's units (BOP: millimetres) and faces (M, 3) or ``None``.

    Raises
    ------
    FileNotFoundError
    ValueError
        No vertex element, non-finite vertices, faces that are not triangles or index outside
        the vertices.
    """
    from plyfile import PlyData

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"The model file {p} does not exist.")
    try:
        ply = PlyData.read(str(p))
    except Exception as exc:
        raise ValueError(f"Cannot read the PLY file {p}: {exc}") from None
    if "vertex" not in ply:
        raise ValueError(f"{p} has no vertex element.")
    v = ply["vertex"]
    pts = np.stack([np.asarray(v[k], dtype=np.float64) for k in ("x", "y", "z")], axis=1)
    if len(pts) == 0 or not np.isfinite(pts).all():
        raise ValueError(f"{p}: expected finite vertices, got {len(pts)} with non-finite ones.")
    faces = None
    if "face" in ply and ply["face"].count:
        data = ply["face"].data
        name = data.dtype.names[0]
        lists = data[name]
        if any(len(f) != 3 for f in lists):
            raise ValueError(f"{p}: only triangle faces are supported.")
        faces = np.asarray(np.stack(lists), dtype=np.int64)
        if faces.min() < 0 or faces.max() >= len(pts):
            raise ValueError(f"{p}: a face indexes a vertex outside 0..{len(pts) - 1}.")
    return pts, faces


def write_bop_ply(path: str | os.PathLike[str], points_mm: ArrayLike,
                  faces: ArrayLike | None = None) -> Path:
    """Write a binary PLY model (vertices in millimetres, float64 so that metres read back
    as written; optional triangle faces)."""
    from plyfile import PlyData, PlyElement

    from solvers.validation import check_points

    P = check_points(points_mm, "points_mm")
    vert = np.empty(len(P), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    vert["x"], vert["y"], vert["z"] = P[:, 0], P[:, 1], P[:, 2]
    elements = [PlyElement.describe(vert, "vertex")]
    if faces is not None:
        F = np.asarray(faces, dtype=np.int32)
        if F.ndim != 2 or F.shape[1] != 3:
            raise ValueError(f"Expected `faces` to have shape (M, 3), got {F.shape}.")
        face = np.empty(len(F), dtype=[("vertex_indices", "i4", (3,))])
        face["vertex_indices"] = F
        elements.append(PlyElement.describe(face, "face"))
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    PlyData(elements, text=False).write(str(p))
    return p


def _rotation_about(axis: NDArray[np.float64], angle: float) -> NDArray[np.float64]:
    from scipy.spatial.transform import Rotation

    a = np.asarray(axis, dtype=np.float64)
    return Rotation.from_rotvec(a / np.linalg.norm(a) * angle).as_matrix()


def symmetry_transforms(info: dict[str, Any], *, max_sym_disc_step: float = 0.01,
                        scale: float = 1.0 / MM) -> NDArray[np.float64]:
    """The symmetry transformations of a ``models_info.json`` entry, as the BOP toolkit builds
    them: the identity and the discrete symmetries, each composed with every step of the
    discretised continuous symmetries (``ceil(pi / max_sym_disc_step)`` steps per turn).

    Parameters
    ----------
    info : dict
        One object's entry (millimetres).
    max_sym_disc_step : float
        The toolkit's bound on the step, as a fraction of the diameter travelled by the point
        furthest from the axis.
    scale : float
        Multiplies the translations (default: millimetres to metres).

    Returns
    -------
    ndarray, shape (K, 4, 4)
    """
    disc = [np.eye(4)]
    for s in info.get("symmetries_discrete", []) or []:
        S = np.asarray(s, dtype=np.float64).reshape(4, 4).copy()
        S[:3, 3] *= scale
        disc.append(S)
    cont = []
    for s in info.get("symmetries_continuous", []) or []:
        axis = np.asarray(s["axis"], dtype=np.float64)
        offset = np.asarray(s["offset"], dtype=np.float64) * scale
        n = int(math.ceil(math.pi / max_sym_disc_step))
        for i in range(n):
            C = np.eye(4)
            C[:3, :3] = _rotation_about(axis, i * 2.0 * math.pi / n)
            C[:3, 3] = offset - C[:3, :3] @ offset
            cont.append(C)
    if not cont:
        return np.stack(disc)
    return np.stack([C @ D for D in disc for C in cont])


def load_bop_targets(path: str | os.PathLike[str]) -> list[BOPTarget]:
    """Read a targets file (``test_targets_bop19.json``: a list of ``{scene_id, im_id, obj_id,
    inst_count}``), in its order.

    Raises
    ------
    ValueError
        Not a list of such records; a target listed twice.
    """
    p = Path(path)
    data = _json(p)
    if not isinstance(data, list):
        raise ValueError(f"Expected {p} to hold a list of targets, got {type(data).__name__}.")
    out, seen = [], set()
    for k, t in enumerate(data):
        try:
            tgt = BOPTarget(int(t["scene_id"]), int(t["im_id"]), int(t["obj_id"]),
                            int(t.get("inst_count", 1)))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{p}: target {k} is not a {{scene_id, im_id, obj_id, inst_count}} "
                             f"record ({exc!r}).") from None
        key = (tgt.scene_id, tgt.im_id, tgt.obj_id)
        if key in seen:
            raise ValueError(f"{p}: target {key} is listed twice.")
        if tgt.inst_count < 1:
            raise ValueError(f"{p}: target {key} has inst_count {tgt.inst_count} (< 1).")
        seen.add(key)
        out.append(tgt)
    return out


def _transform(R: Any, t: Any, where: str) -> NDArray[np.float64]:
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.size != 9 or t.size != 3 or not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise ValueError(f"{where}: expected cam_R_m2c (9 numbers) and cam_t_m2c (3), got "
                         f"{R.size} and {t.size} (or non-finite values).")
    T = np.eye(4)
    T[:3, :3] = R.reshape(3, 3)
    T[:3, 3] = t.reshape(3) / MM
    return T


class BOPDataset:
    """A BOP dataset folder, read lazily; each scene's JSON files are read once.

    Parameters
    ----------
    root : path
        The dataset folder (holding ``models/`` and the split folders).
    split : str
        The split folder's name (``"test"``).

    Raises
    ------
    FileNotFoundError
        ``root``, ``root/models/models_info.json`` or ``root/split`` missing.
    """

    def __init__(self, root: str | os.PathLike[str], split: str = "test") -> None:
        self.root = Path(root)
        self.split = str(split)
        if not self.root.is_dir():
            raise FileNotFoundError(f"The BOP dataset folder {self.root} does not exist.")
        info_path = self.root / "models" / "models_info.json"
        self.models_info: dict[int, dict[str, Any]] = _int_keys(_json(info_path), info_path)
        if not (self.root / self.split).is_dir():
            raise FileNotFoundError(f"The split folder {self.root / self.split} does not exist.")
        self._scenes: dict[tuple[int, str], dict[int, Any]] = {}
        self._objects: dict[int, BOPObject] = {}

    def __repr__(self) -> str:
        return f"BOPDataset({str(self.root)!r}, split={self.split!r})"

    @property
    def obj_ids(self) -> list[int]:
        return sorted(self.models_info)

    def scene_ids(self) -> list[int]:
        """The scene folders of the split, sorted."""
        return sorted(int(p.name) for p in (self.root / self.split).iterdir()
                      if p.is_dir() and p.name.isdigit())

    def scene_dir(self, scene_id: int) -> Path:
        return self.root / self.split / f"{int(scene_id):06d}"

    def _scene_json(self, scene_id: int, name: str) -> dict[int, Any]:
        key = (int(scene_id), name)
        if key not in self._scenes:
            path = self.scene_dir(scene_id) / f"{name}.json"
            self._scenes[key] = _int_keys(_json(path), path)
        return self._scenes[key]

    def _image_entry(self, scene_id: int, im_id: int, name: str) -> Any:
        d = self._scene_json(scene_id, name)
        if int(im_id) not in d:
            raise KeyError(f"Image {im_id} of scene {scene_id} is not in {name}.json.")
        return d[int(im_id)]

    def image_ids(self, scene_id: int) -> list[int]:
        return sorted(self._scene_json(scene_id, "scene_camera"))

    def camera(self, scene_id: int, im_id: int) -> tuple[NDArray[np.float64], float]:
        """The image's intrinsic matrix ``K`` (3, 3), pixels, and its ``depth_scale`` (depth
        image units to millimetres)."""
        cam = self._image_entry(scene_id, im_id, "scene_camera")
        K = np.asarray(cam.get("cam_K", []), dtype=np.float64)
        if K.size != 9 or not np.isfinite(K).all():
            raise ValueError(f"scene_camera.json of scene {scene_id}, image {im_id}: expected "
                             f"cam_K with 9 numbers, got {K.size}.")
        scale = float(cam.get("depth_scale", 1.0))
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"scene_camera.json of scene {scene_id}, image {im_id}: depth_scale "
                             f"must be positive, got {scale}.")
        return K.reshape(3, 3), scale

    def instances(self, scene_id: int, im_id: int) -> list[BOPInstance]:
        """The image's annotated instances (ground truth in metres), in file order."""
        gts = self._image_entry(scene_id, im_id, "scene_gt")
        infos = None
        if (self.scene_dir(scene_id) / "scene_gt_info.json").is_file():
            infos = self._image_entry(scene_id, im_id, "scene_gt_info")
        out = []
        for k, g in enumerate(gts):
            where = f"scene_gt.json of scene {scene_id}, image {im_id}, instance {k}"
            visib = None if infos is None or k >= len(infos) else infos[k].get("visib_fract")
            out.append(BOPInstance(k, int(g["obj_id"]), _transform(g["cam_R_m2c"],
                                                                     g["cam_t_m2c"], where),
                                   None if visib is None else float(visib)))
        return out

    def image_path(self, scene_id: int, im_id: int, kind: str) -> Path:
        """``rgb``, ``gray`` or ``depth`` image file of an image (``.png``, else ``.jpg``,
        ``.tif``)."""
        folder = self.scene_dir(scene_id) / kind
        for ext in (".png", ".jpg", ".tif"):
            p = folder / f"{int(im_id):06d}{ext}"
            if p.is_file():
                return p
        raise FileNotFoundError(f"No {kind} image {int(im_id):06d}.* in {folder}.")

    def frame(self, scene_id: int, im_id: int, *, color: bool = True) -> Any:
        """The image as an :class:`~certpose.geometry.rgbd.RGBDFrame` (depth in metres,
        camera = world frame)."""
        from certpose.geometry.rgbd import CameraIntrinsics, load_rgbd

        K, scale = self.camera(scene_id, im_id)
        depth_path = self.image_path(scene_id, im_id, "depth")
        color_path = None
        if color:
            try:
                color_path = self.image_path(scene_id, im_id, "rgb")
            except FileNotFoundError:
                color_path = self.image_path(scene_id, im_id, "gray")
        from certpose.geometry.rgbd import read_image

        h, w = read_image(depth_path, "depth").shape[:2]
        # metres = value * depth_scale / 1000; written as a division, as load_rgbd takes it.
        return load_rgbd(color_path, depth_path, CameraIntrinsics.from_matrix(K, w, h),
                         depth_scale=MM / scale)

    def mask_visib(self, scene_id: int, im_id: int, gt_id: int,
                   shape: tuple[int, int] | None = None) -> NDArray[np.bool_]:
        """The visible-silhouette mask of instance ``gt_id`` (``mask_visib/``), (H, W) bool."""
        from certpose.geometry.rgbd import read_image

        p = self.scene_dir(scene_id) / "mask_visib" / f"{int(im_id):06d}_{int(gt_id):06d}.png"
        if not p.is_file():
            raise FileNotFoundError(f"The mask {p} does not exist.")
        m = read_image(p, "mask")
        if m.ndim == 3:
            m = m.any(axis=2)
        if shape is not None and m.shape != tuple(shape):
            raise ValueError(f"The mask {p} has shape {m.shape}, the image {tuple(shape)}.")
        return np.asarray(m) > 0

    def object(self, obj_id: int) -> BOPObject:
        """The object model ``obj_id`` in metres, read once per dataset object."""
        obj_id = int(obj_id)
        if obj_id not in self._objects:
            if obj_id not in self.models_info:
                raise KeyError(f"Object {obj_id} is not in models_info.json (it has "
                               f"{self.obj_ids}).")
            info = self.models_info[obj_id]
            pts, faces = read_bop_ply(self.root / "models" / f"obj_{obj_id:06d}.ply")
            diameter = float(info.get("diameter", math.nan))
            if not (math.isfinite(diameter) and diameter > 0):
                raise ValueError(f"models_info.json: object {obj_id} has no positive diameter.")
            # Rounded to the nanometre: a division by 1000 leaves one-ulp noise in about 2% of
            # the coordinates, enough to change a model built from them; vertices given to the
            # micrometre (as millimetres with three decimals) read back as written in metres.
            self._objects[obj_id] = BOPObject(obj_id, np.round(pts / MM, 9), faces, diameter / MM,
                                              symmetry_transforms(info), info)
        return self._objects[obj_id]

    def targets(self, path: str | os.PathLike[str] | None = None) -> list[BOPTarget]:
        """The targets of ``path`` (default ``<root>/test_targets_bop19.json``)."""
        return load_bop_targets(self.root / "test_targets_bop19.json" if path is None else path)


def group_targets(targets: Iterable[BOPTarget]) -> dict[tuple[int, int], list[BOPTarget]]:
    """Targets grouped by image ``(scene_id, im_id)``, in first-appearance order."""
    out: dict[tuple[int, int], list[BOPTarget]] = {}
    for t in targets:
        out.setdefault((t.scene_id, t.im_id), []).append(t)
    return out


@lru_cache(maxsize=8)
def open_dataset(root: str, split: str) -> BOPDataset:
    """A :class:`BOPDataset` shared by the calls of one process (a worker's)."""
    return BOPDataset(root, split)
