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
