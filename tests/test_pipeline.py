"""The whole pipeline: pose recovery on the synthetic scene and a real YCB-Video frame, object
models, errors, the CLI and bad input."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose.cli import main
from certpose.estimation.pipeline import PoseParams, pose_errors, run_demo, run_ycbv
from certpose.geometry.features import ArrayBackbone, FPFHBackbone
from certpose.geometry.objects import ObjectModel, object_from_points, object_from_views
from certpose.geometry.rgbd import CameraIntrinsics, RGBDFrame
from solvers.lie import make_transform
from tests.conftest import box_surface, require_data, strict_json


@pytest.mark.slow  # over 3 s
def test_demo_recovers_the_mug_pose():
    res = run_demo(rng=0)
    assert res.success, res.message
    e = res.errors
    assert e is not None
    assert e.translation <= 0.01
    assert e.symmetry_axis_deg is not None and e.symmetry_axis_deg <= 5.0
    assert e.add_s <= 0.01
    assert np.isfinite(res.log_likelihood)
    # The winner is at least as likely as the refined eq. (2) minimiser.
    assert res.log_likelihood >= res.eq2_refined_log_likelihood - 1e-6
    d = res.to_dict()
    assert np.asarray(d["T_camera_object"]).shape == (4, 4)
    json.dumps(d, allow_nan=False)


@pytest.mark.slow  # over 3 s
def test_real_ycbv_frame_mug():
    root = require_data("ycbv")
    require_data("ycbv", "0000", "000001-meta.mat")
    res = run_ycbv(root, "0000/000001", "025_mug")
    assert res.success, res.message
    e = res.errors
    assert e.translation <= 0.01, e
    assert e.symmetry_axis_deg <= 5.0, e
    assert e.add_s <= 0.01, e
    # The certifier ran on eq. (2) (it may run out of time, but it must say so in a certificate).
    assert res.certificate is not None, res.certificate_message
    assert res.certificate.message and np.isfinite(res.certificate.upper_bound)
    # It bounds eq. (2) at its minimiser; the returned pose was refined on eq. (1).
    assert not res.pose_is_certified
    assert res.certificate.problem in res.certificate_scope
    assert ("NOT the returned pose" in res.certificate_scope
            or "no pose is certified" in res.certificate_scope)
    data = res.to_dict()
    assert data["certified_pose"]["problem"] == res.certificate.problem
    assert not np.allclose(data["certified_pose"]["T_camera_object"], res.T_camera_object)
    assert data["modes"][0]["log_likelihood"] == pytest.approx(res.log_likelihood)


def test_pose_errors_judge_the_symmetry_axis_only():
    rng = np.random.default_rng(0)
    pts = rng.normal(scale=0.03, size=(200, 3))
    T = make_transform(Rotation.from_rotvec([0.3, 0.2, -0.1]).as_matrix(), [0.1, 0.0, 0.6])
    spun = T @ make_transform(Rotation.from_rotvec([0.0, 0.0, 1.0]).as_matrix(), [0.0, 0.0, 0.0])  # about the z axis
    e = pose_errors(spun, T, pts, symmetry_axis=(0, 0, 1))
    assert e.symmetry_axis_deg == pytest.approx(0.0, abs=1e-5)
    assert e.rotation_deg == pytest.approx(math.degrees(1.0), rel=1e-6)
    assert e.translation == pytest.approx(0.0, abs=1e-12)
    assert 0 < e.add_s < e.add
    same = pose_errors(T, T, pts)
    assert same.add == pytest.approx(0.0, abs=1e-12) and same.symmetry_axis_deg is None
    tilted = T @ make_transform(Rotation.from_rotvec([0.1, 0.0, 0.0]).as_matrix(), [0.0, 0.0, 0.0])
    assert pose_errors(tilted, T, pts, symmetry_axis=(0, 0, 1)).symmetry_axis_deg == pytest.approx(
        math.degrees(0.1), rel=1e-6)


def test_object_from_points_and_views():
    rng = np.random.default_rng(1)
    # A 6 x 4 x 3 cm box surface.
    pts = box_surface(rng, np.array([0.06, 0.04, 0.03]), 800)
    obj = object_from_points(pts, FPFHBackbone(), voxel_size=0.005, name="box")
    assert isinstance(obj, ObjectModel) and obj.name == "box"
    assert obj.descriptors.shape == (len(obj), 33)
    np.testing.assert_allclose(np.linalg.norm(obj.normals, axis=1), 1.0, atol=1e-6)
    # Outward normals: they point away from the centre.
    assert np.mean(np.einsum("ij,ij->i", obj.normals, obj.points - obj.centroid) > 0) > 0.9
    with pytest.raises(ValueError, match="voxel_size"):
        object_from_points(pts, FPFHBackbone(), voxel_size=0.0)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        object_from_points(np.zeros((10, 2)), FPFHBackbone(), voxel_size=0.005)
    # Views: a fronto-parallel wall seen by a camera; the mask picks its middle.
    cam = CameraIntrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)
    mask = np.zeros((48, 64), bool)
    mask[10:38, 12:52] = True
    frame = RGBDFrame(None, np.full((48, 64), 0.4), cam, make_transform(np.eye(3), [0, 0, -0.4]))
    view_obj = object_from_views([(frame, mask)], FPFHBackbone(), voxel_size=0.005)
    assert np.allclose(view_obj.points[:, 2], 0.0, atol=1e-9)  # the wall is at world z = 0
    with pytest.raises(ValueError, match="empty"):
        object_from_views([(frame, np.zeros((48, 64), bool))], FPFHBackbone(), voxel_size=0.005)
    # An image backbone (per-pixel descriptors, as DINO): averaged per voxel, unit rows.
    pix = np.random.default_rng(2).normal(size=(48, 64, 5))
    img_obj = object_from_views([(frame, mask)], ArrayBackbone(pix), voxel_size=0.005)
    assert img_obj.dim == 5 and len(img_obj) == len(view_obj)
    np.testing.assert_allclose(np.linalg.norm(img_obj.descriptors, axis=1), 1.0, atol=1e-9)
    with pytest.raises(ValueError, match="views"):
        object_from_views([], FPFHBackbone(), voxel_size=0.005)
    try:
        import cv2  # noqa: F401
    except ImportError:  # without OpenCV a view needs a mask (GrabCut is unavailable)
        with pytest.raises(ValueError, match="OpenCV"):
            object_from_views([frame], FPFHBackbone(), voxel_size=0.005)


def test_missing_files_and_bad_names(tmp_path):
    with pytest.raises(OSError):
        run_ycbv(tmp_path, "0000/000001", "025_mug")
    root = require_data("ycbv")
    with pytest.raises(OSError):
        run_ycbv(root, "0000/000001", "025_mug", tmp_path / "nope.xyz")
    with pytest.raises(KeyError):
        run_ycbv(root, "0000/000001", "002_master_chef_can")
    with pytest.raises(ValueError, match="voxel_size"):
        PoseParams(voxel_size=-1.0)


def test_cli_errors_are_one_line(tmp_path, capsys):
    assert main(["pose", "--ycbv", str(tmp_path / "missing")]) == 2  # bad input
    err = capsys.readouterr().err
    assert "not a directory" in err and err.count("\n") == 1
    root = require_data("ycbv")
    assert main(["pose", "--ycbv", str(root), "--object", "no_such_object"]) == 2
    assert "no_such_object" in capsys.readouterr().err


def test_cli_ycbv_writes_json(tmp_path, capsys):
    root = require_data("ycbv")
    out = tmp_path / "pose.json"
    code = main(["pose", "--ycbv", str(root), "--frame", "0000/000002", "--object",
                 "061_foam_brick", "--model", str(root / "models" / "061_foam_brick" / "points.xyz"),
                 "--no-certify", "--json", str(out)])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "T_camera_object" in text and "ADD-S" in text
    data = strict_json(out.read_text())
    assert np.asarray(data["T_camera_object"]).shape == (4, 4)
    assert data["errors"]["add_s"] <= 0.01
    assert data["certificate"] is None and data["certificate_message"] == "not requested"
    assert data["pose_is_certified"] is False and data["certified_pose"] is None
    assert "certificate: no certificate" in text and "CERTIFIED" not in text


@pytest.mark.parametrize("option, name, message", [
    ("--particles", "p.dat", "--particles {} must end in .npz"),  # NumPy wrote p.dat.npz
    ("--plot", "m.dat", "--plot {}: unsupported image type 'dat'"),  # failed after the work
    ("--plot", "m", "--plot {}: unsupported image type '(none)'"),
])
def test_cli_pose_output_names_checked_before_the_work(tmp_path, capsys, option, name, message):  # type: ignore[no-untyped-def]
    from certpose.cli import main

    path = tmp_path / name
    assert main(["pose", "--demo", "--samples", "50", option, str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message.format(path) in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_cli_pose_demo_samples_writes_particles(tmp_path, capsys):  # type: ignore[no-untyped-def]
    """`certpose pose --demo --samples N --particles OUT.npz`: N particles of T_camera_object."""
    from certpose.cli import main
    from certpose.sampling import PoseDistribution

    out = tmp_path / "particles.npz"
    js = tmp_path / "pose.json"
    assert main(["pose", "--demo", "--samples", "500", "--particles", str(out),
                 "--json", str(js)]) == 0
    text = capsys.readouterr().out
    assert "pose distribution (importance sampler): 500 particles" in text and "Pareto-k" in text
    dist = PoseDistribution.load(out)
    assert len(dist) == 500 and abs(dist.weights.sum() - 1) < 1e-9
    import json

    payload = json.loads(js.read_text())
    T = np.asarray(payload["T_camera_object"])
    # The particles are in the camera frame, around the returned pose (the mug spins about
    # its axis, so compare positions).
    assert np.median(np.linalg.norm(dist.translations - T[:3, 3], axis=1)) < 0.02
    assert payload["sampling"]["particles"] == 500 and payload["sampling"]["ess"] > 0
    # Each mode line says how far the mode's mean turns from the returned pose and the truth,
    # about the mug's axis too: read the heaviest mode's back against the saved particles.
    from certpose.sampling.plots import axis_angles
    from solvers.lie import rotation_error_deg

    mode = dist.modes()[0]
    line = next(x for x in text.splitlines() if x.startswith("  mode 0: "))
    found = re.search(r"rotation ([\d.]+) deg \(([-+][\d.]+) about the axis\) from the returned pose, "
                      r"([\d.]+) deg \(([-+][\d.]+) about the axis\) from the truth", line)
    assert found, line
    from certpose.data.synthetic import make_mug_scene

    gt = make_mug_scene(rng=0).T_camera_object  # the demo's scene at its default seed
    for (angle, turn), T_ref in zip([found.group(1, 2), found.group(3, 4)], [T, gt], strict=True):
        assert abs(float(angle) - rotation_error_deg(mode.rotation, T_ref[:3, :3])) < 0.06
        assert abs(float(turn) - np.degrees(axis_angles(mode.rotation[None], (0, 0, 1), T_ref)[0])) < 0.06
    # The demo has no YCB-Video frame or object (their defaults do not apply).
    assert payload["input"]["demo"] is True
    assert payload["input"]["frame"] is None and payload["input"]["object"] is None


@pytest.mark.slow
@pytest.mark.parametrize("method, label", [("de", "Nevergrad TwoPointsDE, population weighted"), ("mcmc", "random-walk Metropolis")])
def test_cli_pose_demo_baseline_and_plot(tmp_path, capsys, method, label):  # type: ignore[no-untyped-def]
    """`certpose pose --demo --samples N --method de|mcmc --plot OUT.png` on the same target."""
    import struct

    from certpose.cli import main
    from certpose.sampling import PoseDistribution

    out, png = tmp_path / "p.npz", tmp_path / "m.png"
    assert main(["pose", "--demo", "--samples", "300", "--method", method, "--particles", str(out),
                 "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert f"pose distribution ({label}): 300 particles" in text and "mode 0: mass" in text, text
    # The same evaluation budget as the importance sampler's default (10,000 + 11 x 500).
    assert "15500 eq. (1) evaluations" in text or method == "mcmc"
    assert len(PoseDistribution.load(out)) == 300
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and struct.unpack(">II", data[16:24]) == (1200, 600)
    # The demo's exact hidden-handle arc is shaded (light green) on the axis panel.
    import matplotlib.image

    img = matplotlib.image.imread(str(png))[..., :3]
    assert np.count_nonzero((img[..., 1] > img[..., 0] + 0.04) & (img[..., 1] > img[..., 2] + 0.04)) > 1000


@pytest.mark.slow
def test_cli_pose_demo_calibrated(tmp_path, capsys):  # type: ignore[no-untyped-def]
    """`certpose pose --demo --samples N --method calibrated`: exact draws around the MLE's basins."""
    from certpose.cli import main
    from certpose.sampling import PoseDistribution

    out = tmp_path / "c.npz"
    assert main(["pose", "--demo", "--samples", "400", "--method", "calibrated",
                 "--particles", str(out)]) == 0
    text = capsys.readouterr().out
    assert "pose distribution (calibrated: basins x model error): 400 particles" in text, text
    assert "independent draws 400" in text and "basins of" in text and "mode 0: mass" in text
    d = PoseDistribution.load(out)
    assert len(d) == 400 and np.allclose(d.weights, 1 / 400)


def test_cli_pose_plot_and_method_need_samples(tmp_path, capsys):  # type: ignore[no-untyped-def]
    from certpose.cli import main

    assert main(["pose", "--demo", "--plot", str(tmp_path / "m.png")]) == 2  # bad input
    assert "--plot needs --samples" in capsys.readouterr().err
    assert main(["pose", "--demo", "--method", "de"]) == 2
    assert "--method needs --samples" in capsys.readouterr().err
    assert main(["pose", "--demo", "--samples", "10", "--plot",
                 str(tmp_path / "missing" / "m.png")]) == 2
    assert "missing" in capsys.readouterr().err


def test_cli_pose_particles_need_samples(tmp_path, capsys):  # type: ignore[no-untyped-def]
    from certpose.cli import main

    assert main(["pose", "--demo", "--particles", str(tmp_path / "p.npz")]) == 2
    assert "--particles needs --samples" in capsys.readouterr().err
    assert main(["pose", "--demo", "--samples", "10", "--particles",
                 str(tmp_path / "missing" / "p.npz")]) == 2


@pytest.mark.slow  # two MLEs
def test_a_box_with_almost_no_evidence_is_warned_about(caplog):
    # A 5 x 5 pixel box at the image's corner: 2 positives for the mug's 2288 model points and
    # a pose 43 cm off: returned, but as "little_evidence" (not a success), and the log says how
    # little it rests on. A real box does neither.
    import logging

    root = require_data("ycbv", "0000", "000001-box.txt").parents[1]
    with caplog.at_level(logging.WARNING, logger="certpose.estimation.mle"):
        res = run_ycbv(root, "0000/000001", "025_mug", classifier="best_buddies", box=(0, 0, 5, 5))
    warned = [r.getMessage() for r in caplog.records if "little evidence" in r.getMessage()]
    assert len(warned) == 1 and "only 2 occupied voxel(s)" in warned[0], warned
    assert res.errors.add_s > 0.1  # the pose it warns about is wrong
    assert not res.success and res.status == "little_evidence" and "little evidence" in res.message
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="certpose.estimation.mle"):
        res = run_ycbv(root, "0000/000001", "025_mug", classifier="best_buddies")
    assert not [r for r in caplog.records if "little evidence" in r.getMessage()]
    assert res.errors.add_s < 0.01 and res.success and res.status == "converged"


def test_box_only_bad_input_is_refused_before_any_work(tmp_path, capsys):
    root = require_data("ycbv", "0000", "000001-box.txt").parents[1]
    with pytest.raises(ValueError, match="x1 > x0"):
        run_ycbv(root, "0000/000001", "025_mug", classifier="best_buddies", box=(10, 10, 5, 5))
    with pytest.raises(ValueError, match="classifier"):
        run_ycbv(root, "0000/000001", "025_mug", classifier="boxes")
    with pytest.raises(ValueError, match="region of interest"):
        run_ycbv(root, "0000/000001", "025_mug", box=(0, 0, 10, 10))  # mask classifier
    with pytest.raises(KeyError, match="no 2-D box"):
        run_ycbv(root, "0000/000001", "004_sugar_box", classifier="best_buddies")
    from certpose.estimation.pipeline import estimate_pose

    with pytest.raises(ValueError, match="region of interest"):
        estimate_pose(None, None, classifier="mask", box=(0, 0, 10, 10))
    # The CLI: one-line errors, exit code 2.
    base = ["pose", "--ycbv", str(root), "--frame", "0000/000001", "--object", "025_mug",
            "--no-certify"]
    for extra, needle in (
        (["--classifier", "best-buddies", "--box", "10", "10", "5", "5"], "x1 > x0"),
        (["--classifier", "best-buddies", "--box", "700", "0", "800", "9"], "outside the 640x480"),
        (["--classifier", "best-buddies", "--box-margin", "-3"], "--box-margin"),
        (["--box", "0", "0", "10", "10"], "need --classifier best-buddies"),
    ):
        assert main(base + extra) == 2, extra
        err = capsys.readouterr().err
        assert needle in err and err.count("\n") == 1, (extra, err)
    assert main(["pose", "--demo", "--classifier", "best-buddies"]) == 2
    assert "needs --ycbv" in capsys.readouterr().err
    assert main(base[:4] + ["0000/000001", "--object", "004_sugar_box", "--classifier",
                            "best-buddies"]) == 2
    err = capsys.readouterr().err
    assert "no 2-D box" in err and err.count("\n") == 1


@pytest.mark.slow  # over 3 s
def test_box_only_pose_with_an_appearance_model_from_another_scene():
    """No mask: the potted-meat can's box in 0049 and best buddies with a model built from the
    views of scene 0002 (never evaluated on 0002)."""
    from certpose.estimation.pipeline import build_ycbv_object_model
    from certpose.model.classifier import box_mask
    from certpose.model.grid import OCCUPIED, scene_grid_spec

    root = require_data("ycbv")
    require_data("ycbv", "0049", "000001-box.txt")
    name = "010_potted_meat_can"
    model = build_ycbv_object_model(root, ["0002/000001", "0002/000010", "0002/000020"], name)
    res = run_ycbv(root, "0049/000001", name, object_model=model, classifier="best_buddies")
    assert res.success, res.message
    assert res.errors.add_s <= 0.01, res.errors
    cls = res.classification
    assert cls.method == "best_buddies" and "in the box" in cls.message
    # Every positive, and every voxel above c_min, is seen inside the box.
    from certpose.io.ycbv import load_ycbv_frame

    yf = load_ycbv_frame(root, "0049/000001")
    inside = box_mask(yf.object_box(name), yf.frame.shape)
    above = np.argwhere((cls.log_p > cls.c_min) & (np.asarray(res.scene.state) == OCCUPIED))
    assert cls.num_positive > 20 and above.shape[0] > cls.num_positive
    u, v, _ = yf.intrinsics.project(scene_grid_spec(res.scene).centres(above))
    assert inside[np.floor(v + 0.5).astype(int), np.floor(u + 0.5).astype(int)].all()


@pytest.mark.slow  # over 3 s
def test_cli_box_only_geometry_model(tmp_path, capsys):
    root = require_data("ycbv")
    out = tmp_path / "pose.json"
    code = main(["pose", "--ycbv", str(root), "--frame", "0000/000002", "--object",
                 "061_foam_brick", "--classifier", "best-buddies", "--no-certify", "--json",
                 str(out)])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "best buddies in the box of box.txt (no mask)" in text and "in the box" in text
    data = strict_json(out.read_text())
    assert data["input"]["classifier"] == "best-buddies" and data["input"]["box"] is None
    assert data["errors"]["add_s"] <= 0.01


@pytest.mark.slow  # the demo, then its mode set (10 s at most)
def test_pose_demo_certify_modes_lists_the_regions(tmp_path, capsys):
    """`certpose pose --demo --certify-modes`: eq. (2)'s certified mode set, its regions on
    the command line and in the JSON, around the certified minimiser (camera frame)."""
    from certpose.cli import main

    out = tmp_path / "demo.json"
    assert main(["pose", "--demo", "--certify-modes", "60", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "eq. (2) mode set: CERTIFIED" in text and "region 0: rotation within" in text
    d = json.loads(out.read_text())
    ms = d["mode_set"]
    assert ms["status"] == "certified" and ms["success"] and ms["regions"]
    assert ms["margin"] == pytest.approx(0.02 * ms["best_cost"])
    assert ms["lower_bound"] <= ms["best_cost"]
    # The certified eq. (2) minimiser (camera frame) lies in a listed region.
    from solvers.certify.mode_set import ModeRegion

    T = np.asarray(d["certified_pose"]["T_camera_object"]) if d["certified_pose"] else None
    regions = [ModeRegion(np.asarray(r["T_target_source"])[:3, :3],
                          np.radians(r["rotation_radius_deg"]),
                          np.asarray(r["T_target_source"])[:3, 3], r["translation_half_width"],
                          r["cost"], r["num_boxes"]) for r in ms["regions"]]
    if T is not None:
        assert any(r.contains(T) for r in regions)
    assert any(r.contains(np.asarray(ms["T_target_source"])) for r in regions)
