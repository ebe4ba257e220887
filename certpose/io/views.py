"""Posed RGB-D views of an object from a JSON manifest (any camera), for object models with
appearance (``certpose object build --posed-views``).

The manifest::

    {
      "intrinsics": [fx, fy, cx, cy],          # pixels; a view may give its own
      "depth_scale": 1000,                     # raw depth units per metre; a view may give its own
      "views": [
        {"name": "table/0001",                 # optional; "SCENE/FRAME" names the scene (provenance)
         "color": "0001-color.png", "depth": "0001-depth.png", "mask": "0001-mask.png",
         "T_camera_object": [[...], [...], [...], [0, 0, 0, 1]]},   # maps model points into the camera
        ...
      ]
    }

Relative paths are read from the manifest's folder; a mask is non-zero on the object's pixels.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["load_posed_views"]


def _fail(path: Path, what: str) -> ValueError:
    return ValueError(f"Posed-view manifest {path}: {what}.")


def _intrinsics(path: Path, where: str, value: Any) -> tuple[float, float, float, float]:
    try:
        k = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        k = np.zeros(0)
    if k.shape != (4,) or not np.all(np.isfinite(k)):
        raise _fail(path, f"{where}`intrinsics` must be [fx, fy, cx, cy], got {value!r}")
    return float(k[0]), float(k[1]), float(k[2]), float(k[3])


def load_posed_views(path: str | os.PathLike[str]) -> list[Any]:
    """Read the posed views a manifest lists (module docstring).

    Parameters
    ----------
    path : path
        The JSON manifest.

    Returns
    -------
    list of PosedView
        In the manifest's order; each view's name is its ``name`` or its colour image's stem.

    Raises
    ------
    FileNotFoundError
        The manifest or an image it names does not exist.
    ValueError
        Not JSON, no views, a view without ``color``/``depth``/``mask``/``T_camera_object``,
        intrinsics that are not four finite numbers, a non-positive depth scale, a pose that
        is not a rigid transform, images of different sizes, an empty mask.
    """
    from certpose.geometry.appearance import PosedView
    from certpose.geometry.rgbd import load_rgbd, read_mask
    from solvers.lie import make_transform, project_to_so3
    from solvers.validation import check_transform

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"The posed-view manifest {path} does not exist.")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise _fail(path, f"not JSON ({exc})") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("views"), list) or not doc["views"]:
        raise _fail(path, 'expected an object with a non-empty "views" list')
    base = path.parent
    views = []
    for i, v in enumerate(doc["views"]):
        where = f"view {i}: "
        if not isinstance(v, dict):
            raise _fail(path, f"{where}expected an object, got {type(v).__name__}")
        missing = [k for k in ("color", "depth", "mask", "T_camera_object") if k not in v]
        if missing:
            raise _fail(path, f"{where}missing {', '.join(missing)}")
        k = _intrinsics(path, where, v.get("intrinsics", doc.get("intrinsics")))
        scale = v.get("depth_scale", doc.get("depth_scale", 1000.0))
        if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
            raise _fail(path, f"{where}`depth_scale` must be a positive number, got {scale!r}")
        try:
            # Poses written as text are orthonormal to a few digits: accept 1e-3, then snap.
            T = check_transform(np.asarray(v["T_camera_object"], dtype=np.float64),
                                "T_camera_object", atol=1e-3)
        except (TypeError, ValueError) as exc:
            raise _fail(path, f"{where}{exc}") from exc
        T = make_transform(project_to_so3(T[:3, :3]), T[:3, 3])
        color, depth, mask_path = (base / str(v[key]) for key in ("color", "depth", "mask"))
        try:  # the image size is the depth image's
            frame = load_rgbd(color, depth, k, depth_scale=float(scale))
        except ValueError as exc:
            raise _fail(path, f"{where}{str(exc).rstrip('.')}") from exc
        height, width = frame.depth.shape
        try:
            mask = read_mask(mask_path, (height, width))
        except ValueError as exc:
            raise _fail(path, f"{where}{str(exc).rstrip('.')}") from exc
        views.append(PosedView(frame, mask, T, name=str(v.get("name", color.stem))))
    return views
