"""Plausibility of the camera and of the object's observed size: wrong intrinsics or depth
scales are refused or reported, never posed "successfully"."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from certpose.cli import main
from certpose.geometry.plausibility import check_intrinsics, observed_lateral_extent
from certpose.geometry.rgbd import CameraIntrinsics

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ycbv"
needs_ycbv = pytest.mark.skipif(not DATA.is_dir() and not os.environ.get("CI"),
                                reason="YCB-Video data not found")
YCBV_K = (1066.778, 1067.487, 312.9869, 241.3109)


@pytest.mark.parametrize("k, match", [
    ((106.68, 106.75, 312.99, 241.31), "fx = 106.68 px gives a horizontal field of view of 143"),
    ((1066.778, 1067.487, 3000.0, -500.0), r"principal point .* outside the 640 x 480 image"),
    ((1066.778, 1067.487, -1.0, 240.0), "principal point"),
    ((1066.778, 1067.487, 320.0, 481.0), "principal point"),
    ((10000.0, 10000.0, 320.0, 240.0), "field of view of 3.67"),
    ((1066.778, 106.75, 312.99, 241.31), "fy = 106.75 px gives a vertical field of view"),
    ((600.0, 1300.0, 320.0, 240.0), "differ by more than a factor 2"),
    ((241.31, 312.99, 1066.778, 1067.487), "principal point"),  # the order confused
], ids=["fx_tenth", "pp_far", "cx_negative", "cy_below", "telephoto", "fy_tenth", "aspect",
        "order"])
def test_implausible_intrinsics_are_refused(k, match):
    with pytest.raises(ValueError, match=match):
        check_intrinsics(CameraIntrinsics(*k, 640, 480))


@pytest.mark.parametrize("k, size", [
    (YCBV_K, (640, 480)),  # YCB-Video (Asus Xtion colour)
    ((615.0, 615.0, 320.0, 240.0), (640, 480)),  # RealSense D435 colour
    ((365.0, 365.0, 256.0, 212.0), (512, 424)),  # Kinect v2 depth
    ((40.0, 40.0, 20.0, 15.0), (40, 30)),
], ids=["ycbv", "d435", "kinect2", "tiny"])
def test_real_cameras_pass(k, size):
    check_intrinsics(CameraIntrinsics(*k, *size))


def test_observed_lateral_extent_ignores_clutter_behind_and_scales_with_the_focal_length():
    rng = np.random.default_rng(0)
    obj = rng.uniform(-0.05, 0.05, (500, 3)) + [0.0, 0.0, 1.0]  # 0.1 m cube at 1 m
    clutter = rng.uniform(-0.05, 0.05, (100, 3)) * [1, 1, 0] + [0.0, 0.0, 2.0]  # same ray, 2 m
    base = observed_lateral_extent(obj)
    assert 0.12 < base < 0.16  # the face's diagonal (percentile box, perspective)
    assert observed_lateral_extent(np.vstack([obj, clutter])) < 1.2 * base
    # A focal length ten times too small back-projects ten times wider at the same depth.
    wide = obj.copy()
    wide[:, :2] *= 10
    assert observed_lateral_extent(wide) == pytest.approx(10 * base, rel=1e-9)


def _files():
    return [str(DATA / "0000/000001-color.png"), str(DATA / "0000/000001-depth.png")]


@needs_ycbv
@pytest.mark.parametrize("k", [("106.68", "106.75", "312.99", "241.31"),
                               ("1066.778", "1067.487", "3000", "-500")],
                         ids=["fx_tenth", "pp_outside"])
def test_pose_cli_refuses_the_issues_intrinsics_before_the_work(tmp_path, capsys, k):
    mask = tmp_path / "m.png"
    Image.fromarray(np.ones((480, 640), np.uint8)).save(mask)
    model = DATA / "models/025_mug/points.xyz"
    code = main(["pose", "--rgbd", *_files(), "--intrinsics", *k, "--depth-scale", "10000",
                 "--model", str(model), "--mask", str(mask)])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "field of view" in err or "principal point" in err


@needs_ycbv
@pytest.mark.parametrize("extra, fix", [(["--depth-scale", "1000"], "--depth-scale"),
                                        (["--depth-scale", "10000", "--voxel-size", "0.00001"],
                                         "--voxel-size")], ids=["depth_scale", "voxel_size"])
def test_grid_errors_name_the_commands_options(tmp_path, capsys, extra, fix):
    """The library's "crop with `bounds` or `roi_mask`" names no option the command has."""
    mask = tmp_path / "m.png"
    Image.fromarray(np.ones((480, 640), np.uint8)).save(mask)
    model = DATA / "models/025_mug/points.xyz"
    code = main(["pose", "--rgbd", *_files(), "--intrinsics", *map(str, YCBV_K),
                 "--model", str(model), "--mask", str(mask), *extra])
    err = capsys.readouterr().err
    assert code == 2
    assert "roi_mask" not in err and "`bounds`" not in err and fix in err


@pytest.mark.slow
@needs_ycbv
def test_a_focal_length_five_times_too_small_is_not_a_success(tmp_path):
    """fx / 5 passes the field-of-view check (113 degrees) but the mug then spans 3.6 times its
    size: reported implausible_scale; the right intrinsics pose it successfully."""
    from certpose.estimation.pipeline import run_rgbd
    from certpose.io.ycbv import load_ycbv_frame

    yf = load_ycbv_frame(DATA, "0000/000001")
    mask = tmp_path / "mug.png"
    Image.fromarray(yf.object_mask("025_mug").astype(np.uint8) * 255).save(mask)
    model = DATA / "models/025_mug/points.xyz"
    fx, fy, cx, cy = YCBV_K
    for div, ok in ((5.0, False), (1.0, True)):
        r = run_rgbd(*_files(), (fx / div, fy / div, cx, cy), model_path=model,
                     depth_scale=10000, mask_path=mask)
        assert r.success is ok, r.message
        assert (r.status == "implausible_scale") is (not ok)
        if not ok:
            assert "--intrinsics" in r.message and "times the model's size" in r.message


@needs_ycbv
def test_a_flat_model_is_bad_input_not_a_qhull_dump(tmp_path, capsys):
    """Once a 1,200-character Qhull message and exit 1."""
    flat = tmp_path / "flat.xyz"
    rng = np.random.default_rng(0)
    np.savetxt(flat, np.c_[rng.uniform(-0.05, 0.05, (500, 2)), np.zeros(500)])
    mask = tmp_path / "m.png"
    Image.fromarray(np.ones((480, 640), np.uint8)).save(mask)
    code = main(["pose", "--rgbd", *_files(), "--intrinsics", *map(str, YCBV_K),
                 "--depth-scale", "10000", "--model", str(flat), "--mask", str(mask)])
    err = capsys.readouterr().err
    assert code == 2 and "are flat" in err and "Qhull" not in err and len(err) < 300
