"""The YCB-Video loader, on the real frames in ../shared/data/ycbv."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from certpose.io.ycbv import load_class_names, load_model_points, load_ycbv_boxes, load_ycbv_frame
from tests.conftest import require_data

OBJECTS = ["009_gelatin_box", "025_mug", "061_foam_brick"]


@pytest.fixture(scope="module")
def root() -> Path:
    require_data("ycbv", "0000", "000001-meta.mat")
    return require_data("ycbv")


@pytest.fixture(scope="module")
def frame(root):
    return load_ycbv_frame(root, "0000/000001")


def test_intrinsics_depth_scale_and_classes(root, frame):
    import imageio.v3 as iio
    import scipy.io

    meta = scipy.io.loadmat(root / "0000" / "000001-meta.mat")
    cam = frame.frame.intrinsics
    assert (cam.width, cam.height) == (640, 480)
    np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy], [1066.778, 1067.487, 312.9869, 241.3109])
    raw = iio.imread(root / "0000" / "000001-depth.png")
    np.testing.assert_allclose(frame.frame.depth, raw / 10000.0)
    assert float(meta["factor_depth"].ravel()[0]) == 10000.0
    assert frame.class_names == OBJECTS
    assert frame.class_indexes == [8, 14, 21]
    assert load_class_names(root)[13] == "025_mug"
    assert frame.frame.color.shape == (480, 640, 3) and frame.frame.color.dtype == np.uint8
    np.testing.assert_array_equal(frame.frame.T_world_camera, np.eye(4))


def test_poses_match_meta(root, frame):
    import scipy.io

    poses = scipy.io.loadmat(root / "0000" / "000001-meta.mat")["poses"]
    for k, name in enumerate(OBJECTS):
        T = frame.poses[name]
        np.testing.assert_allclose(T[:3, :], poses[:, :, k], atol=1e-5)
        np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(T[:3, :3]) > 0


@pytest.mark.parametrize("name", OBJECTS)
def test_ground_truth_projects_onto_object_mask(root, frame, name):
    # The pose maps model points into the camera frame: visible model points land in the mask
    # and at the measured depth.
    model = load_model_points(root / "models" / name / "points.xyz")
    assert model.shape == (2621, 3)
    T = frame.poses[name]
    q = model @ T[:3, :3].T + T[:3, 3]
    u, v, z = frame.frame.intrinsics.project(q)
    u, v = np.rint(u).astype(int), np.rint(v).astype(int)
    mask = frame.object_mask(name)
    depth = frame.frame.depth[v, u]
    visible = (depth > 0) & (np.abs(depth - z) < 0.01)
    assert visible.mean() > 0.15
    assert mask[v[visible], u[visible]].mean() > 0.9
    ys, xs = np.nonzero(mask)
    assert xs.min() - 5 <= np.median(u) <= xs.max() + 5 and ys.min() - 5 <= np.median(v) <= ys.max() + 5


def test_object_mask(frame):
    mask = frame.object_mask("025_mug")
    np.testing.assert_array_equal(mask, frame.label == 14)
    assert mask.sum() > 1000
    with pytest.raises(KeyError, match="004_sugar_box"):
        frame.object_mask("004_sugar_box")


def test_missing_files_are_named(root, tmp_path):
    with pytest.raises(FileNotFoundError, match="999999-color.png"):
        load_ycbv_frame(root, "0000/999999")
    with pytest.raises(FileNotFoundError, match="nowhere"):
        load_ycbv_frame(tmp_path / "nowhere")
    for bad in ("0000", "0000/", "/000001", "0000/000001/x"):  # not <scene>/<frame>
        with pytest.raises(ValueError, match="<scene>/<frame>"):
            load_ycbv_frame(root, bad)
    # A frame folder lacking only its meta.mat (links to the real files, nothing copied).
    (tmp_path / "0000").mkdir()
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "classes.txt").symlink_to(root / "models" / "classes.txt")
    for suffix in ("color.png", "depth.png", "label.png"):
        (tmp_path / "0000" / f"000001-{suffix}").symlink_to(root / "0000" / f"000001-{suffix}")
    with pytest.raises(FileNotFoundError, match="000001-meta.mat"):
        load_ycbv_frame(tmp_path, "0000/000001")
    (tmp_path / "0000" / "000001-meta.mat").write_bytes(b"not a mat file")
    with pytest.raises(ValueError, match="000001-meta.mat"):
        load_ycbv_frame(tmp_path, "0000/000001")


def test_model_points_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="points.xyz"):
        load_model_points(tmp_path / "points.xyz")
    bad = tmp_path / "bad.xyz"
    bad.write_text("1 2 3\n4 five 6\n")
    with pytest.raises(ValueError, match="bad.xyz"):
        load_model_points(bad)
    nan = tmp_path / "nan.xyz"
    nan.write_text("1 2 3\nnan 5 6\n")
    with pytest.raises(ValueError, match="NaN"):
        load_model_points(nan)
    good = tmp_path / "good.xyz"
    good.write_text("1 2 3\n4 5 6\n")
    np.testing.assert_array_equal(load_model_points(good), [[1, 2, 3], [4, 5, 6]])


def test_boxes_hold_the_labelled_pixels(root, frame):
    assert sorted(frame.boxes) == sorted(OBJECTS)
    for name in OBJECTS:
        x0, y0, x1, y1 = frame.object_box(name)
        rows, cols = np.nonzero(frame.object_mask(name))
        inside = (cols >= x0 - 1) & (cols <= x1 + 1) & (rows >= y0 - 1) & (rows <= y1 + 1)
        assert inside.mean() > 0.99, name
    with pytest.raises(KeyError, match="no 2-D box for object '004_sugar_box'"):
        frame.object_box("004_sugar_box")


def test_malformed_box_files_name_the_line(tmp_path):
    path = tmp_path / "000001-box.txt"
    cases = {
        "025_mug 1 2 3\n": "line 1: expected 'name x0 y0 x1 y1'",
        "025_mug 1 2 3 4\n025_mug 1 2 3 4\n": "line 2: object '025_mug' listed twice",
        "\n025_mug 10 20 5 30\n": "line 2: `box` must have x1 > x0",
        "025_mug 1 2 three 4\n": "line 1",
        "025_mug 700 10 800 20\n": "outside the 640x480 image",
    }
    for text, match in cases.items():
        path.write_text(text)
        with pytest.raises(ValueError, match=match):
            load_ycbv_boxes(path, (480, 640))
    with pytest.raises(FileNotFoundError, match="missing-box.txt"):
        load_ycbv_boxes(tmp_path / "missing-box.txt")
    path.write_text("025_mug 1.5 2 30 40.25\n\n009_gelatin_box 0 0 10 10\n")
    assert load_ycbv_boxes(path) == {"025_mug": (1.5, 2.0, 30.0, 40.25),
                                     "009_gelatin_box": (0.0, 0.0, 10.0, 10.0)}
