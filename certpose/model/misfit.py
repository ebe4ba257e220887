"""How well a posed object model explains the measured depth: the model error of one estimate.

Eq. (1) is as sharp as its object model and depth are exact. The model-error kernel of the pose
distribution (:meth:`~certpose.sampling.PoseDistribution.with_model_error`) carries what eq. (1)
leaves out; this module measures it at the returned pose, so that the kernel can be as wide as
the data say rather than fixed.

At a pose ``T`` (scene frame) each model point ``p_i`` that a view of the scene sees
(visibility ``v_i >= 0.5`` from that view's camera: facing it and not hidden by the object
itself, :mod:`certpose.model.visibility`) is projected to its nearest pixel ``u``; its residual
is ``e_i = d(u) - z_i``, the measured depth minus the point's camera depth (metres; positive:
the model stands in front of the measured surface). Pixels without depth (0) or outside the
image are skipped, and so are points more than ``occlusion`` metres behind the measured surface
(another object in front of them: they carry no information on the model). The misfit is the
robust scale about zero ``r = 1.4826 median |e_i|`` (metres): the standard deviation for
Gaussian residuals of zero mean, and it counts a bias too (a model that is too large, or a
pose a few degrees off). Silhouette pixels that see the background behind the object are
outliers the median ignores while they are fewer than half the points.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.validation import check_points, check_transform

__all__ = ["DepthMisfit", "depth_misfit", "lever_arm", "misfit_kernel"]

log = logging.getLogger(__name__)

#: ``1 / Phi^{-1}(3/4)``: the median absolute value of a standard normal variable is 1 / this.
MAD_SCALE = 1.482602218505602


@dataclass(frozen=True)
class DepthMisfit:
    """The depth misfit of a posed model (see the module).

    Attributes
    ----------
    misfit : float
        ``r = 1.4826 median |e|``, metres (``nan`` when no point was scored).
    median : float
        Median signed residual ``d(u) - z``, metres (positive: the model in front).
    num_scored : int
        Residuals the misfit is the scale of (points seen with a depth, summed over the views).
    num_occluded : int
        Points seen with a depth but more than ``occlusion`` behind the measured surface.
    num_visible : int
        Points seen by some view (visibility >= 0.5), with depth or not.
    """

    misfit: float
    median: float
    num_scored: int
    num_occluded: int
    num_visible: int

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def lever_arm(points: ArrayLike) -> float:
    """RMS distance (metres) of the points (N, 3) from their centroid: how far a rotation of one
    radian about the centroid moves them, on average."""
    p = check_points(points, "points", min_points=1)
    return float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))


def _model_arrays(object_model: Any) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    model = getattr(object_model, "model", object_model)
    points = check_points(getattr(model, "points", None), "object_model.points", min_points=1)
    normals = getattr(model, "normals", None)
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        if normals.shape != points.shape:
            raise ValueError(f"Expected `object_model.normals` to have shape {points.shape}, "
                             f"got {normals.shape}.")
    return points, normals


def _view_residuals(frame: Any, world: NDArray[np.float64], seen: NDArray[np.bool_]
                    ) -> NDArray[np.float64]:
    """Residuals ``d(u) - z`` of the seen points (world frame) in one view; nan where the
    pixel has no depth, lies outside the image, or the point is behind the camera."""
    row, col, z, inside = frame.pixels_of(world)
    inside &= seen
    out = np.full(len(world), np.nan)
    d = np.zeros(len(world))
    d[inside] = np.asarray(frame.depth)[row[inside], col[inside]]
    ok = inside & (d > 0)
    out[ok] = d[ok] - z[ok]
    return out

def depth_misfit(scene: Any, object_model: Any, T_scene_object: ArrayLike, *,
                 occlusion: float = 0.02, grazing: float = 0.25) -> DepthMisfit:
    """The depth misfit of ``object_model`` at ``T_scene_object`` against the depth images the
    scene keeps (see the module).

    Parameters
    ----------
    scene : SceneField
        Built from RGB-D frames (its ``frames``, :func:`~certpose.model.scene.build_scene_field`).
    object_model : ObjectModel or BuiltObjectModel
        Points (N, 3) in the object frame, metres; with ``normals`` the points are weighed by
        their visibility from each camera (facing it, not self-occluded), without them every
        point in front of the camera counts.
    T_scene_object : (4, 4) array_like
        The pose, scene (world) frame.
    occlusion : float
        Metres (> 0): a point further than this behind the measured surface is taken as
        occluded by something else and not scored.
    grazing : float
        ``n . d`` at which a point counts as fully facing the camera (in ``(0, 1]``).

    Returns
    -------
    DepthMisfit
    """
    from certpose.model.freespace import scene_frames

    frames = scene_frames(scene)
    if not (np.isfinite(occlusion) and occlusion > 0):
        raise ValueError(f"`occlusion` must be a positive number of metres, got {occlusion}.")
    T = check_transform(T_scene_object, "T_scene_object")
    points, normals = _model_arrays(object_model)
    R, t = T[:3, :3], T[:3, 3]
    world = points @ R.T + t
    table = None
    if normals is not None:
        from certpose.model.visibility import cached_visibility_table

        table = cached_visibility_table(points, normals, grazing=grazing)
    res, any_seen = [], np.zeros(len(points), dtype=bool)
    for f in frames:
        cam = np.asarray(f.T_world_camera, dtype=np.float64)[:3, 3]
        seen = (np.ones(len(points), dtype=bool) if table is None
                else table.visibility(points, R.T @ (cam - t)) >= 0.5)
        any_seen |= seen
        e = _view_residuals(f, world, seen)
        res.append(e[np.isfinite(e)])
    e = np.concatenate(res)
    kept = e[e >= -float(occlusion)]
    if kept.size == 0:
        log.debug("depth misfit: no model point seen with a depth")
        return DepthMisfit(float("nan"), float("nan"), 0, int(e.size), int(any_seen.sum()))
    return DepthMisfit(float(MAD_SCALE * np.median(np.abs(kept))), float(np.median(kept)),
                       int(kept.size), int(e.size - kept.size), int(any_seen.sum()))


def misfit_kernel(misfit: float, lever_arm: float, *, rotation_gain: float,
                  translation_gain: float) -> tuple[float, float]:
    """The model-error kernel's ``(rotation_sigma, translation_sigma)`` (radians, metres per
    axis) for a depth misfit ``misfit`` (metres) of a model with RMS lever arm ``lever_arm``
    (metres): ``rotation_gain * misfit / lever_arm`` (a turn that moves the points by about
    ``rotation_gain * misfit``) and ``translation_gain * misfit``."""
    for name, v in (("misfit", misfit), ("rotation_gain", rotation_gain),
                    ("translation_gain", translation_gain)):
        if not (np.isfinite(v) and v >= 0):
            raise ValueError(f"Expected `{name}` to be finite and >= 0, got {v}.")
    if not (np.isfinite(lever_arm) and lever_arm > 0):
        raise ValueError(f"Expected `lever_arm` to be finite and > 0, got {lever_arm}.")
    return float(rotation_gain * misfit / lever_arm), float(translation_gain * misfit)
