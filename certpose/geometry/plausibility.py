"""Plausibility of a camera and of an object's observed size: a wrong input that still gives a
pose (focal lengths ten times too small, a principal point off the image, a depth scale ten
times off) is reported instead of being posed "successfully".

Two checks: :func:`check_intrinsics` refuses pinhole intrinsics no depth camera has for its
image size; :func:`judge_observed_extent` compares the lateral extent of the voxels classified
as the object with the object model's size (a wrong focal length or depth scale scales the
former, not the latter).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "MAX_FIELD_OF_VIEW_DEG",
    "MIN_FIELD_OF_VIEW_DEG",
    "MAX_EXTENT_RATIO",
    "check_intrinsics",
    "check_model_points",
    "observed_lateral_extent",
    "judge_observed_extent",
]

log = logging.getLogger(__name__)

MAX_FIELD_OF_VIEW_DEG = 120.0
"""Widest field of view (horizontal or vertical) accepted for a pinhole camera: depth cameras
see 55-90 degrees; wider lenses are fisheyes, which a pinhole model does not describe."""

MIN_FIELD_OF_VIEW_DEG = 5.0
"""Narrowest field of view accepted (a telephoto lens no RGB-D camera has)."""

MAX_ASPECT = 2.0
"""Largest ratio of the two focal lengths (pixels are nearly square)."""

MAX_EXTENT_RATIO = 2.0
"""Largest ratio of the object's observed lateral extent to the model's size (plus a few voxels
of classification slack) before the camera or depth scale is judged wrong."""


def _fov_deg(size: int, focal: float) -> float:
    return math.degrees(2.0 * math.atan(size / (2.0 * focal)))


def check_intrinsics(intrinsics: Any) -> None:
    """Refuse intrinsics implausible for their image size.

    Parameters
    ----------
    intrinsics : CameraIntrinsics
        ``fx``, ``fy``, ``cx``, ``cy`` in pixels with the image's ``width`` and ``height``.

    Raises
    ------
    ValueError
        The principal point lies outside the image, a field of view (``2 atan(size / 2f)``) is
        outside [:data:`MIN_FIELD_OF_VIEW_DEG`, :data:`MAX_FIELD_OF_VIEW_DEG`], or the focal
        lengths differ by more than a factor :data:`MAX_ASPECT`. The message gives the values.
    """
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    w, h = intrinsics.width, intrinsics.height
    if not (0.0 <= cx <= w and 0.0 <= cy <= h):
        raise ValueError(
            f"The principal point (cx, cy) = ({cx:g}, {cy:g}) px lies outside the {w} x {h} "
            f"image; it is normally near the centre ({w / 2:g}, {h / 2:g}): check the "
            "intrinsics' order (fx, fy, cx, cy) and units (pixels).")
    for axis, size, focal in (("horizontal", w, fx), ("vertical", h, fy)):
        fov = _fov_deg(size, focal)
        if not MIN_FIELD_OF_VIEW_DEG <= fov <= MAX_FIELD_OF_VIEW_DEG:
            name = "fx" if axis == "horizontal" else "fy"
            lo = size / (2.0 * math.tan(math.radians(MAX_FIELD_OF_VIEW_DEG / 2)))
            hi = size / (2.0 * math.tan(math.radians(MIN_FIELD_OF_VIEW_DEG / 2)))
            raise ValueError(
                f"{name} = {focal:g} px gives a {axis} field of view of {fov:.3g} degrees for an "
                f"image {size} px {'wide' if axis == 'horizontal' else 'high'}; a depth camera's "
                f"focal length is {lo:.0f}-{hi:.0f} px at that size: check the intrinsics (are "
                "they for another image resolution?).")
    if max(fx, fy) > MAX_ASPECT * min(fx, fy):
        raise ValueError(f"fx = {fx:g} px and fy = {fy:g} px differ by more than a factor "
                         f"{MAX_ASPECT:g}: check the intrinsics' order (fx, fy, cx, cy).")


MIN_MODEL_THICKNESS = 1e-4
"""Thinnest model accepted, as a fraction of its extent (the surface sampling's Delaunay
triangulation fails on flat input)."""


def check_model_points(points: Any, *, name: str = "model points") -> None:
    """Refuse object model points that span no volume (flat, collinear or coincident).

    Raises
    ------
    ValueError
        With the model's thickness and extent: the object models are sampled on the surface
        of a solid, which a flat point set does not bound.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 4:
        return  # the model builder reports shapes and counts
    centred = pts - pts.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    spans = np.ptp(centred @ vt.T, axis=0)  # along the principal axes, widest first
    if not spans[2] > MIN_MODEL_THICKNESS * spans[0]:
        raise ValueError(
            f"The {name} are flat: {spans[2]:.3g} m thick across {spans[0]:.3g} m; an object "
            "model needs points on a solid's surface (a flat sheet bounds no volume).")


def observed_lateral_extent(points_camera: NDArray[np.float64]) -> float:
    """Lateral size (metres) of points in the camera frame, measured at their median depth.

    Each point's image-plane offset ``(x / z, y / z)`` is scaled by the median depth, so
    points far behind the object (clutter in a detector's box) do not widen it; a focal
    length or depth scale ``s`` times too small makes it ``s`` times too large. The 2nd-98th
    percentile box's diagonal, so that a few stray voxels do not count.
    """
    p = np.asarray(points_camera, dtype=np.float64)
    p = p[p[:, 2] > 0]
    if p.shape[0] < 2:
        return 0.0
    z = float(np.median(p[:, 2]))
    xy = p[:, :2] / p[:, 2:3] * z
    lo, hi = np.percentile(xy, [2.0, 98.0], axis=0)
    return float(np.linalg.norm(hi - lo))


def judge_observed_extent(result: Any, model_points: Any, *, voxel_size: float) -> Any:
    """``result`` (a :class:`~certpose.estimation.pipeline.PoseResult`), reported
    ``implausible_scale`` when the object's positives are far wider than the model.

    Parameters
    ----------
    result : PoseResult
        With its ``classification``, ``scene`` and ``T_world_camera``.
    model_points : (M, 3) array_like
        The object model's points (metres).
    voxel_size : float
        The scene's voxel size (metres): the classification's slack.

    Returns
    -------
    PoseResult
        Unchanged when plausible (or when nothing was classified), else with
        ``success=False``, ``status="implausible_scale"`` and a message naming the likely cause.
    """
    cls, scene = result.classification, result.scene
    if cls is None or scene is None or result.T_world_camera is None:
        return result
    ijk = np.argwhere(np.asarray(cls.positive))
    if ijk.shape[0] < 2:
        return result
    world = scene.grid_to_world(ijk.astype(np.float64))
    T_cw = np.linalg.inv(result.T_world_camera)
    observed = observed_lateral_extent(world @ T_cw[:3, :3].T + T_cw[:3, 3])
    pts = np.asarray(model_points, dtype=np.float64)
    size = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    limit = MAX_EXTENT_RATIO * size + 4.0 * voxel_size
    log.debug("observed lateral extent %.3g m, model size %.3g m", observed, size)
    if observed <= limit:
        return result
    message = (
        f"implausible scale: the {ijk.shape[0]} voxels classified as the object span "
        f"{observed:.3g} m across at their median depth, {observed / size:.3g} times the "
        f"model's size ({size:.3g} m); the focal lengths may be too small or the depth scale "
        f"too small (check --intrinsics / --depth-scale). The pose found: {result.message}")
    return dataclasses.replace(result, success=False, status="implausible_scale",
                               message=message)
