"""The classifiers p_O: mask-based (projection + depth check) and best buddies."""

from __future__ import annotations

import math

import numpy as np
import pytest

from certpose.geometry.features import ArrayBackbone
from certpose.geometry.objects import ObjectModel
from certpose.geometry.rgbd import CameraIntrinsics, RGBDFrame
from certpose.model.classifier import (
    ClassifierParams,
    ClassifierStatus,
    box_mask,
    check_box,
    classify_best_buddies,
    classify_from_mask,
)
from certpose.model.grid import EMPTY, OCCUPIED, UNOBSERVED
from certpose.model.scene import SceneField, build_scene_field

CAM = CameraIntrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)


def _step_frame() -> RGBDFrame:
    """A wall at 0.5 m on the left half of the image and at 0.7 m on the right half."""
    depth = np.full((48, 64), 0.5)
    depth[:, 32:] = 0.7
    return RGBDFrame(None, depth, CAM)


def _scene(frame: RGBDFrame) -> SceneField:
    desc = np.tile(np.array([[1.0, 0.0]]), (48 * 64, 1))
    return build_scene_field(frame, ArrayBackbone(desc.reshape(48, 64, 2)), voxel_size=0.01)


def test_mask_classifier_marks_voxels_seen_inside_the_mask():
    frame = _step_frame()
    scene = _scene(frame)
    mask = np.zeros((48, 64), bool)
    mask[:, :32] = True  # the near wall
    cls = classify_from_mask(scene, frame, mask)
    assert cls.success and cls.status is ClassifierStatus.OK and cls.method == "mask"
    idx = np.argwhere(scene.state == OCCUPIED)
    centres = scene.grid_to_world(idx.astype(float))
    near = centres[:, 2] < 0.6
    pos = cls.positive[tuple(idx.T)]
    # Positives are occupied voxels of the near wall; the far wall is negative.
    assert pos.any()
    assert not pos[~near].any()
    assert pos[near].mean() > 0.8
    # Values: log 0.9 at positives, c_min elsewhere (also at non-occupied voxels).
    params = ClassifierParams()
    assert np.all(cls.log_p[cls.positive] == pytest.approx(math.log(0.9)))
    assert np.all(cls.log_p[~cls.positive] == params.c_min)
    assert not cls.positive[scene.state != OCCUPIED].any()


def test_mask_classifier_depth_check_rejects_background_behind_the_mask():
    frame = _step_frame()
    scene = _scene(frame)
    mask = np.zeros((48, 64), bool)
    mask[:, 30:34] = True  # straddles the depth step
    cls = classify_from_mask(scene, frame, mask, depth_tolerance=0.02)
    idx = np.argwhere(cls.positive)
    depth_of = scene.grid_to_world(idx.astype(float))[:, 2]
    # Every positive voxel centre agrees with a wall (0.5 or 0.7 m) within the tolerance.
    assert np.all(np.minimum(abs(depth_of - 0.5), abs(depth_of - 0.7)) <= 0.02 + 1e-9)


def test_mask_classifier_bad_input():
    frame = _step_frame()
    scene = _scene(frame)
    with pytest.raises(ValueError, match="empty"):
        classify_from_mask(scene, frame, np.zeros((48, 64), bool))
    with pytest.raises(ValueError, match="shape"):
        classify_from_mask(scene, frame, np.ones((10, 10), bool))
    with pytest.raises(ValueError, match="mask"):
        classify_from_mask(scene, frame)  # no mask given, frame has none
    with pytest.raises(ValueError, match="depth_tolerance"):
        classify_from_mask(scene, frame, np.ones((48, 64), bool), depth_tolerance=-1.0)


def _hand_scene(desc_list: list[np.ndarray]) -> SceneField:
    shape = (len(desc_list), 1, 1)
    d = desc_list[0].size
    desc = np.zeros((*shape, d))
    state = np.full(shape, OCCUPIED, dtype=np.int8)
    for i, v in enumerate(desc_list):
        desc[i, 0, 0] = v
    return SceneField(0.01, np.zeros(3), shape, desc, state)


def test_best_buddies_mutual_nearest_neighbours():
    e = np.eye(4)
    # Scene voxels: e0, e1, -e0 (dissimilar), e3; the object has e0 and e1 only.
    scene = _hand_scene([e[0], e[1], -e[0], e[3]])
    obj = ObjectModel(np.array([[0.0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]]), e[[0, 1, 1]])
    cls = classify_best_buddies(scene, obj, scene_neighbors=1, min_similarity=0.5)
    assert cls.positive[:, 0, 0].tolist() == [True, True, False, False]
    assert cls.method == "best_buddies" and cls.num_positive == 2
    # With the threshold at 1 only exact matches count; at -1 and k=4 every voxel whose best
    # object point lists it among its 4 nearest is a buddy (all of them here).
    loose = classify_best_buddies(scene, obj, scene_neighbors=4, min_similarity=-1.0)
    assert loose.positive.all()


def test_best_buddies_no_positive_is_reported_not_raised():
    e = np.eye(3)
    scene = _hand_scene([e[0], e[0]])
    obj = ObjectModel(np.array([[0.0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]]), -e[[0, 0, 0]])
    cls = classify_best_buddies(scene, obj, min_similarity=0.0)
    assert not cls.success and cls.status is ClassifierStatus.NO_POSITIVES
    assert "no occupied voxel" in cls.message


def test_best_buddies_bad_input():
    e = np.eye(3)
    scene = _hand_scene([e[0], e[1]])
    obj = ObjectModel(np.zeros((3, 3)) + np.arange(3)[:, None] * 0.01, np.eye(4)[:3])
    with pytest.raises(ValueError, match="dimensions differ"):
        classify_best_buddies(scene, obj)
    obj3 = ObjectModel(np.arange(9.0).reshape(3, 3) * 0.01, e)
    with pytest.raises(ValueError, match="scene_neighbors"):
        classify_best_buddies(scene, obj3, scene_neighbors=0)
    with pytest.raises(ValueError, match="min_similarity"):
        classify_best_buddies(scene, obj3, min_similarity=2.0)
    empty = SceneField(0.01, np.zeros(3), (2, 1, 1), np.zeros((2, 1, 1, 3)),
                       np.array([EMPTY, UNOBSERVED], dtype=np.int8).reshape(2, 1, 1))
    with pytest.raises(ValueError, match="no occupied voxel"):
        classify_best_buddies(empty, obj3)


def test_classifier_params_validation():
    with pytest.raises(ValueError, match="log_p_positive"):
        ClassifierParams(log_p_positive=0.1)
    with pytest.raises(ValueError, match="c_min"):
        ClassifierParams(c_min=-0.01)
    with pytest.raises(ValueError, match="finite"):
        ClassifierParams(c_min=float("-inf"))


def _textured_step():
    """The step frame with a random unit descriptor per pixel, its scene, and an object whose
    points copy the descriptors of three voxels of each wall (exact best buddies)."""
    frame = _step_frame()
    rng = np.random.default_rng(3)
    desc = rng.normal(size=(48, 64, 8))
    scene = build_scene_field(frame, ArrayBackbone(desc), voxel_size=0.01)
    idx = np.argwhere(scene.state == OCCUPIED)
    centres = scene.grid_to_world(idx.astype(float))
    near = np.flatnonzero(centres[:, 2] < 0.6)
    far = np.flatnonzero(centres[:, 2] > 0.6)
    pick = np.concatenate([near[[5, len(near) // 2, -5]], far[[5, len(far) // 2, -5]]])
    z = scene.descriptors[tuple(idx[pick].T)].astype(np.float64)
    obj = ObjectModel(centres[pick] - centres[pick].mean(0), z)
    return frame, scene, obj, idx, centres, pick


def _pixels(frame, centres):
    u, v, _ = frame.intrinsics.project(centres @ frame.T_camera_world[:3, :3].T
                                       + frame.T_camera_world[:3, 3])
    return np.floor(u + 0.5), np.floor(v + 0.5)


def test_box_restricts_best_buddies_to_voxels_seen_in_it():
    frame, scene, obj, idx, centres, pick = _textured_step()
    params = ClassifierParams(scene_neighbors=1, min_similarity=0.99)
    free = classify_best_buddies(scene, obj, params=params)
    # Without a box the exact copies on both walls are buddies.
    assert free.positive[tuple(idx[pick].T)].all()
    box = (0.0, 0.0, 25.0, 47.0)  # the left, near wall only
    cls = classify_best_buddies(scene, obj, params=params, frame=frame, box=box)
    assert cls.success and "in the box" in cls.message
    u, v = _pixels(frame, centres)
    inside = (u >= 0) & (u <= 25) & (v >= 0) & (v <= 47)
    assert inside.any() and (~inside).any()
    pos = cls.positive[tuple(idx.T)]
    val = cls.log_p[tuple(idx.T)]
    # Voxels seen outside the box are background; inside, positives get log 0.9, the rest
    # log_p_box.
    assert not pos[~inside].any()
    assert np.all(val[~inside] == params.c_min)
    assert np.all(val[inside & pos] == pytest.approx(params.log_p_positive))
    assert np.all(val[inside & ~pos] == pytest.approx(params.log_p_box))
    assert pos[inside].any()
    # The near wall's copies that project into the box stay buddies; the far wall's are gone.
    near_in = [p for p in pick if inside[p]]
    assert near_in and cls.positive[tuple(idx[near_in].T)].all()
    assert not cls.positive[tuple(idx[pick[3:]].T)].any()
    # Non-occupied voxels hold c_min.
    assert np.all(cls.log_p[scene.state != OCCUPIED] == params.c_min)
    # log_p_box=None: the box's non-buddies are negatives too.
    hard = classify_best_buddies(scene, obj, params=ClassifierParams(
        scene_neighbors=1, min_similarity=0.99, log_p_box=None), frame=frame, box=box)
    assert np.array_equal(hard.positive, cls.positive)
    assert np.all(hard.log_p[~hard.positive] == params.c_min)


def test_box_margin_grows_the_box():
    assert box_mask((10, 10, 20, 20), (48, 64)).sum() == 11 * 11
    assert box_mask((10, 10, 20, 20), (48, 64), margin=2).sum() == 15 * 15
    # Clipped at the image border.
    assert box_mask((-5.0, -5.0, 3.0, 3.0), (48, 64)).sum() == 4 * 4


@pytest.mark.parametrize("box, match", [
    ((20, 10, 10, 30), "x1 > x0"),            # wrong order
    ((10, 30, 20, 10), "y1 > y0"),
    ((10, 10, 10, 30), "x1 > x0"),            # empty
    ((70, 10, 90, 30), "outside the 64x48 image"),
    ((-30, -30, -5, -5), "outside"),
    ((1, 2, 3), r"shape \(4,\)"),
    ((1, 2, 3, float("nan")), "finite"),
    ("abcd", "four numbers"),
])
def test_bad_boxes_are_refused(box, match):
    with pytest.raises(ValueError, match=match):
        check_box(box, (48, 64))
    frame, scene, obj, *_ = _textured_step()
    with pytest.raises(ValueError, match=match):
        classify_best_buddies(scene, obj, frame=frame, box=box)


def test_box_needs_its_frame_and_voxels():
    frame, scene, obj, *_ = _textured_step()
    with pytest.raises(ValueError, match="needs the `frame`"):
        classify_best_buddies(scene, obj, box=(0, 0, 10, 10))
    # A box over pixels without depth holds no occupied voxel.
    depth = frame.depth.copy()
    depth[:10, :10] = 0.0
    holed = RGBDFrame(None, depth, CAM)
    rng = np.random.default_rng(0)
    sc = build_scene_field(holed, ArrayBackbone(rng.normal(size=(48, 64, 8))), voxel_size=0.01)
    with pytest.raises(ValueError, match="No occupied voxel"):
        classify_best_buddies(sc, obj, frame=holed, box=(0, 0, 4, 4))


def test_best_buddy_settings_are_validated():
    with pytest.raises(ValueError, match="log_p_box"):
        ClassifierParams(log_p_box=-10.0)  # below c_min
    with pytest.raises(ValueError, match="log_p_box"):
        ClassifierParams(log_p_box=0.0)  # above log_p_positive
    with pytest.raises(ValueError, match="box_margin"):
        ClassifierParams(box_margin=-1.0)
    with pytest.raises(ValueError, match="scene_neighbors"):
        ClassifierParams(scene_neighbors=0)
    with pytest.raises(ValueError, match="min_similarity"):
        ClassifierParams(min_similarity=1.5)
