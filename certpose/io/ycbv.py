"""Loader for the YCB-Video frame format.

A frame ``<root>/<scene>/<frame>`` consists of ``<frame>-color.png`` (RGB), ``<frame>-depth.png``
(uint16, metres = value / ``factor_depth``), ``<frame>-label.png`` (per-pixel class index,
0 = background) and ``<frame>-meta.mat`` (``intrinsic_matrix``, ``factor_depth``,
``cls_indexes`` (1-based into ``models/classes.txt``) and ``poses`` (3, 4, n): ``[R | t]`` maps
model points into the camera frame, i.e. ``T_camera_object``), and optionally
``<frame>-box.txt`` (one 2-D box per line, ``name x0 y0 x1 y1`` in pixels: what a detector
gives). Model points are ``<root>/models/<name>/points.xyz``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from certpose.geometry.rgbd import CameraIntrinsics, RGBDFrame, load_rgbd, read_image
from solvers.lie import make_transform, project_to_so3

if TYPE_CHECKING:
    from certpose.geometry.appearance import PosedView

__all__ = ["YCBVFrame", "load_ycbv_frame", "load_ycbv_boxes", "load_model_points", "load_class_names"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class YCBVFrame:
    """One YCB-Video frame with its labels and ground-truth poses.

    Attributes
    ----------
    frame : RGBDFrame
        Colour, depth (metres) and intrinsics; ``T_world_camera`` is the identity.
    label : ndarray of int, shape (H, W)
        Class index per pixel (0 = background).
    class_names : list of str
        Names of the objects annotated in this frame (order of ``meta.mat``).
    class_indexes : list of int
        Their 1-based class indices (the values used in ``label``).
    poses : dict of str to ndarray (4, 4)
        ``T_camera_object`` of each annotated object (rotation projected onto SO(3)).
    name : str
        ``"<scene>/<frame>"``.
    boxes : dict of str to tuple of float
        2-D boxes ``(x0, y0, x1, y1)`` in pixels from ``<frame>-box.txt`` (empty when the frame
        has no such file).
    """

    frame: RGBDFrame
    label: NDArray[np.int64]
    class_names: list[str]
    class_indexes: list[int]
    poses: dict[str, NDArray[np.float64]] = field(repr=False)
    name: str = ""
    boxes: dict[str, tuple[float, float, float, float]] = field(default_factory=dict, repr=False)

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self.frame.intrinsics

    def _index(self, name: str) -> int:
        if name not in self.class_names:
            raise KeyError(f"Object {name!r} is not annotated in frame {self.name}; it has {self.class_names}.")
        return self.class_indexes[self.class_names.index(name)]

    def object_mask(self, name: str) -> NDArray[np.bool_]:
        """Pixels labelled as object ``name``, shape ``(H, W)`` bool.

        Raises ``KeyError`` for an object not in the frame and ``ValueError`` if it has no pixel.
        """
        mask = self.label == self._index(name)
        if not mask.any():
            raise ValueError(f"Object {name!r} has no labelled pixel in frame {self.name}.")
        return mask

    def object_box(self, name: str) -> tuple[float, float, float, float]:
        """The 2-D box ``(x0, y0, x1, y1)`` (pixels) of object ``name`` from ``box.txt``.

        Raises ``KeyError`` when the frame has no box for it.
        """
        if name not in self.boxes:
            have = ", ".join(self.boxes) if self.boxes else "none (no box.txt)"
            raise KeyError(f"Frame {self.name} has no 2-D box for object {name!r}; boxes: {have}.")
        return self.boxes[name]

    def posed_view(self, name: str) -> PosedView:
        """The view of object ``name`` in this frame: its mask and ground-truth ``T_camera_object``.

        Raises ``KeyError`` for an object not annotated in the frame (no pose) and
        ``ValueError`` if it has no labelled pixel.
        """
        from certpose.geometry.appearance import PosedView

        mask = self.object_mask(name)
        return PosedView(self.frame, mask, self.poses[name], self.name)


def load_class_names(root: str | Path) -> list[str]:
    """The class names of ``<root>/models/classes.txt`` (line k = class index k, 1-based)."""
    path = Path(root) / "models" / "classes.txt"
    if not path.is_file():
        raise FileNotFoundError(f"The YCB-Video class list {path} does not exist.")
    return [line.strip() for line in path.read_text().splitlines() if line.strip()]


def _frame_path(root: Path, frame: str, suffix: str) -> Path:
    path = root / f"{frame}-{suffix}"
    if not path.is_file():
        raise FileNotFoundError(f"The YCB-Video file {path} does not exist.")
    return path


def load_ycbv_frame(root: str | Path, frame: str = "0000/000001") -> YCBVFrame:
    """Load one YCB-Video frame.

    Parameters
    ----------
    root : path
        Dataset folder holding ``<scene>/`` folders and ``models/classes.txt``.
    frame : str, optional
        ``"<scene>/<frame>"``, e.g. ``"0000/000001"``.

    Returns
    -------
    YCBVFrame

    Raises
    ------
    FileNotFoundError
        Naming the first missing file.
    ValueError
        For a malformed ``meta.mat``.
    """
    import scipy.io

    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"The YCB-Video folder {root} does not exist.")
    parts = str(frame).split("/")
    if len(parts) != 2 or not all(parts):
        raise ValueError(f'Expected `frame` as "<scene>/<frame>", e.g. "0000/000001", got {frame!r}.')
    color_path = _frame_path(root, frame, "color.png")
    depth_path = _frame_path(root, frame, "depth.png")
    label_path = _frame_path(root, frame, "label.png")
    meta_path = _frame_path(root, frame, "meta.mat")
    keys = ("intrinsic_matrix", "factor_depth", "cls_indexes", "poses")
    try:
        # Only what is used: the file's (H, W, 3) `vertmap` alone takes ~3/4 of a full read.
        meta = scipy.io.loadmat(meta_path, variable_names=keys)
    except Exception as exc:
        raise ValueError(f"Cannot read {meta_path}: {exc}") from exc
    for key in keys:
        if key not in meta:
            raise ValueError(f"{meta_path} has no `{key}` entry.")
    names_all = load_class_names(root)
    label = read_image(label_path, "label")
    if label.ndim != 2:
        raise ValueError(f"Expected the label image {label_path} to have one channel, got shape {label.shape}.")
    height, width = label.shape
    intrinsics = CameraIntrinsics.from_matrix(meta["intrinsic_matrix"], width, height)
    factor = float(np.asarray(meta["factor_depth"]).ravel()[0])
    rgbd = load_rgbd(color_path, depth_path, intrinsics, depth_scale=factor)

    indexes = [int(i) for i in np.asarray(meta["cls_indexes"]).ravel()]
    poses_arr = np.asarray(meta["poses"], dtype=np.float64)
    if poses_arr.ndim == 2:  # a single object is saved as (3, 4)
        poses_arr = poses_arr[:, :, None]
    if poses_arr.shape != (3, 4, len(indexes)):
        raise ValueError(
            f"Expected `poses` in {meta_path} to have shape (3, 4, {len(indexes)}), got {poses_arr.shape}."
        )
    names, poses = [], {}
    for k, idx in enumerate(indexes):
        if not 1 <= idx <= len(names_all):
            raise ValueError(f"Class index {idx} in {meta_path} is outside classes.txt (1..{len(names_all)}).")
        name = names_all[idx - 1]
        # Stored rotations are orthonormal to ~1e-6 only: snap them onto SO(3) so that strict
        # rigid-transform checks downstream accept them (changes entries by ~1e-6).
        T = make_transform(project_to_so3(poses_arr[:, :3, k]), poses_arr[:, 3, k])
        names.append(name)
        poses[name] = T
    box_path = root / f"{frame}-box.txt"
    boxes = load_ycbv_boxes(box_path, (height, width)) if box_path.is_file() else {}
    return YCBVFrame(rgbd, label.astype(np.int64), names, indexes, poses, str(frame), boxes)


def load_ycbv_boxes(path: str | Path, shape: tuple[int, int] | None = None
                    ) -> dict[str, tuple[float, float, float, float]]:
    """Read a YCB-Video ``box.txt``: one ``name x0 y0 x1 y1`` (pixels) per line.

    Parameters
    ----------
    path : path
    shape : (H, W), optional
        The image size; each box is then checked to overlap the image.

    Raises
    ------
    FileNotFoundError
        A missing file.
    ValueError
        A malformed line (naming the file and line), a box in the wrong order or outside the
        image, an object listed twice.
    """
    from certpose.model.classifier import check_box

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"The box file {path} does not exist.")
    boxes: dict[str, tuple[float, float, float, float]] = {}
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        try:
            if len(parts) != 5:
                raise ValueError(f"expected 'name x0 y0 x1 y1', got {len(parts)} fields")
            if parts[0] in boxes:
                raise ValueError(f"object {parts[0]!r} listed twice")
            vals = [float(x) for x in parts[1:]]
            box = check_box(vals, shape if shape is not None else (10**9, 10**9))
        except ValueError as exc:
            raise ValueError(f"{path}, line {n}: {exc}") from exc
        boxes[parts[0]] = box
    return boxes


def load_model_points(path: str | Path) -> NDArray[np.float64]:
    """Read model points (``points.xyz``: one ``x y z`` per line, metres), shape ``(N, 3)``.

    Any format of :func:`certpose.io.points.read_points`, with its checks.
    """
    from certpose.io.points import read_points

    return read_points(path, name="model points")
