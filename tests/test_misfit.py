"""The depth misfit of a posed model (certpose.model.misfit) and the model-error kernel it scales
(PoseParams.model_error="fit"): on the rendered mug scene, where the answer is known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from certpose.data.synthetic import make_mug_scene
from certpose.estimation.pipeline import (
    FALLBACK_MODEL_ERROR,
    PoseParams,
    demo_object_model,
    model_error_kernel,
)
from certpose.geometry.objects import ObjectModel
from certpose.model.grid import OCCUPIED
from certpose.model.misfit import depth_misfit, lever_arm, misfit_kernel
from certpose.model.scene import SceneField, build_scene_field

SIZE = {"width": 320, "height": 240}  # 1.1 mm pixels at the mug


@pytest.fixture(scope="module")
def mug() -> tuple:
    """The rendered mug scene (exact depth), its field, and the demo's model built from views."""
    sc = make_mug_scene(rng=0, **SIZE)
    return sc, build_scene_field(sc.frame, None), demo_object_model(sc)


def scaled(model: ObjectModel, s: float) -> ObjectModel:
    c = model.points.mean(axis=0)
    return ObjectModel(c + s * (model.points - c), model.descriptors, normals=model.normals)


@pytest.mark.slow
def test_exact_model_at_the_truth_fits_within_a_pixel(mug: tuple) -> None:
    sc, scene, obj = mug
    m = depth_misfit(scene, obj, sc.T_camera_object)
    pixel = sc.T_camera_object[2, 3] / sc.intrinsics.fx  # metres per pixel at the mug
    assert m.misfit < pixel, (m, pixel)
    assert abs(m.median) < 0.2 * pixel
    # The handle is hidden behind the occluder: its points are seen by the model's visibility,
    # measured far behind the occluder's surface and left out.
    assert m.num_occluded > 100 and m.num_scored > 400


@pytest.mark.slow
def test_a_model_one_percent_too_large_stands_in_front_by_what_geometry_says(mug: tuple) -> None:
    sc, scene, obj = mug
    T = sc.T_camera_object
    m0 = depth_misfit(scene, obj, T)
    m1 = depth_misfit(scene, scaled(obj, 1.01), T)
    # Each point moves off the surface by h = 1% of its offset from the centroid along its
    # normal, which the camera sees as h / cos(theta) along its line of sight (theta between the
    # normal and the line of sight), for the points facing the camera.
    c = obj.points.mean(axis=0)
    pc = obj.points @ T[:3, :3].T + T[:3, 3]
    view = -pc / np.linalg.norm(pc, axis=1, keepdims=True)
    cos = np.einsum("ij,ij->i", obj.normals @ T[:3, :3].T, view)
    h = 0.01 * np.einsum("ij,ij->i", obj.points - c, obj.normals)
    facing = cos > 0.25
    shift = float(np.median(h[facing] / cos[facing]))
    assert m1.median - m0.median == pytest.approx(shift, rel=0.25)
    assert m1.misfit > m0.misfit + 0.5 * shift
    m2 = depth_misfit(scene, scaled(obj, 1.02), T)
    assert m2.misfit > m1.misfit and m2.median > m1.median


@pytest.mark.slow
@pytest.mark.parametrize("sigma", [0.001, 0.003])
def test_depth_noise_of_known_sigma_is_what_the_misfit_measures(mug: tuple, sigma: float) -> None:
    sc, _, obj = mug
    noisy = make_mug_scene(rng=0, depth_noise=sigma, **SIZE)
    m0 = depth_misfit(build_scene_field(sc.frame, None), obj, sc.T_camera_object)
    m = depth_misfit(build_scene_field(noisy.frame, None), obj, sc.T_camera_object)
    # The robust scale of noise plus the exact render's residuals: at least the noise's sigma
    # (its sum with the residuals of the exact model), at most a third more plus them.
    assert math.hypot(sigma, m0.misfit) * 0.95 <= m.misfit <= 1.35 * sigma + m0.misfit, (m, m0)


@pytest.mark.slow
def test_a_pose_off_by_a_few_degrees_fits_worse(mug: tuple) -> None:
    from scipy.spatial.transform import Rotation

    sc, scene, obj = mug
    T = sc.T_camera_object.copy()
    c = obj.points.mean(axis=0)
    base = depth_misfit(scene, obj, T).misfit
    turn = Rotation.from_rotvec([math.radians(4.0), 0.0, 0.0]).as_matrix()
    T2 = T.copy()
    T2[:3, :3] = T[:3, :3] @ turn
    T2[:3, 3] = T[:3, 3] + T[:3, :3] @ c - T2[:3, :3] @ c
    assert depth_misfit(scene, obj, T2).misfit > 1.5 * base


@pytest.mark.slow
def test_misfit_needs_the_scenes_depth_images_and_a_sane_occlusion(mug: tuple) -> None:
    sc, scene, obj = mug
    bare = SceneField(0.01, np.zeros(3), (2, 2, 2), np.zeros((2, 2, 2, 1)), np.full((2, 2, 2), OCCUPIED, np.int8))
    with pytest.raises(ValueError, match="keeps no depth image"):
        depth_misfit(bare, obj, sc.T_camera_object)
    with pytest.raises(ValueError, match="`occlusion` must be a positive"):
        depth_misfit(scene, obj, sc.T_camera_object, occlusion=0.0)
    with pytest.raises(ValueError, match=r"Expected `T_scene_object`"):
        depth_misfit(scene, obj, np.eye(3))
    far = np.eye(4)
    far[2, 3] = -1.0  # behind the camera: nothing scored
    m = depth_misfit(scene, obj, far)
    assert m.num_scored == 0 and math.isnan(m.misfit)


def test_kernel_scaling_rule() -> None:
    rs, ts = misfit_kernel(0.002, 0.05, rotation_gain=1.5, translation_gain=0.5)
    assert rs == pytest.approx(1.5 * 0.002 / 0.05) and ts == pytest.approx(0.001)
    assert misfit_kernel(0.0, 0.05, rotation_gain=1.0, translation_gain=1.0) == (0.0, 0.0)
    with pytest.raises(ValueError, match="`lever_arm` to be finite and > 0"):
        misfit_kernel(0.002, 0.0, rotation_gain=1.0, translation_gain=1.0)
    with pytest.raises(ValueError, match="`misfit` to be finite"):
        misfit_kernel(float("nan"), 0.05, rotation_gain=1.0, translation_gain=1.0)
    p = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 2.0, 0], [0, -2.0, 0]])
    assert lever_arm(p) == pytest.approx(math.sqrt(2.5))


@pytest.mark.slow
def test_fitted_kernel_follows_the_measured_misfit(mug: tuple) -> None:
    """`model_error="fit"` scales the kernel by the misfit at the pose: wider for a model 2%
    too large than for the exact one; a fixed tuple and None are passed through; a scene
    without depth images falls back to the fixed kernel and says why."""
    sc, scene, obj = mug
    params = PoseParams(model_error="fit", model_error_gains=(2.0, 1.5))
    k = model_error_kernel(scene, obj, sc.T_camera_object, params)
    r = depth_misfit(scene, obj, sc.T_camera_object).misfit
    assert k["rule"] == "fit" and k["misfit"] == pytest.approx(r) and k["dof"] == params.model_error_dof
    assert k["rotation_sigma"] == pytest.approx(2.0 * r / lever_arm(obj.points))
    assert k["translation_sigma"] == pytest.approx(1.5 * r)
    wide = model_error_kernel(scene, scaled(obj, 1.02), sc.T_camera_object, params)
    assert wide["translation_sigma"] > 1.3 * k["translation_sigma"]
    fixed = model_error_kernel(scene, obj, sc.T_camera_object, PoseParams(model_error=(0.01, 0.003)))
    assert (fixed["rule"], fixed["rotation_sigma"], fixed["translation_sigma"]) == ("fixed", 0.01, 0.003)
    none = model_error_kernel(scene, obj, sc.T_camera_object, PoseParams(model_error=None))
    assert none["rule"] == "none" and none["rotation_sigma"] == none["translation_sigma"] == 0.0
    bare = SceneField(0.01, np.zeros(3), (2, 2, 2), np.zeros((2, 2, 2, 1)), np.full((2, 2, 2), OCCUPIED, np.int8))
    fb = model_error_kernel(bare, obj, sc.T_camera_object, params)
    assert fb["rule"].startswith("fixed: ") and "depth image" in fb["rule"]
    assert (fb["rotation_sigma"], fb["translation_sigma"]) == FALLBACK_MODEL_ERROR


@pytest.mark.parametrize("kwargs, match", [
    ({"model_error": "measured"}, "`model_error` must be 'fit', None or"),
    ({"model_error": (0.1,)}, "`model_error` must be 'fit', None or"),
    ({"model_error": (-0.1, 0.002)}, "`model_error` must be 'fit', None or"),
    ({"model_error_gains": (1.0, float("nan"))}, "`model_error_gains` must be"),
    ({"model_error_gains": 2.0}, "`model_error_gains` must be"),
])
def test_model_error_options_are_checked(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        PoseParams(**kwargs)
