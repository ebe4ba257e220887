"""`certpose pose --rgbd COLOR DEPTH`: a user's own RGB-D frame from image files."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from certpose.cli import main
from certpose.estimation.pipeline import run_rgbd

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ycbv"
needs_ycbv = pytest.mark.skipif(not DATA.is_dir() and not os.environ.get("CI"),
                                reason="YCB-Video data not found")
FRAME = "0000/000001"


def _ycbv_inputs(tmp_path: Path, obj: str = "025_mug") -> tuple[list[str], str, list[str]]:
    """The frame's image paths, the object's mask written as a PNG (label == its class), and
    the intrinsics from meta.mat: what a user of another camera would have."""
    from certpose.io.ycbv import load_ycbv_frame

    yf = load_ycbv_frame(DATA, FRAME)
    k = yf.frame.intrinsics
    mask = tmp_path / "mask.png"
    Image.fromarray(yf.object_mask(obj).astype(np.uint8) * 255).save(mask)
    images = [str(DATA / f"{FRAME}-color.png"), str(DATA / f"{FRAME}-depth.png")]
    return images, str(mask), [repr(v) for v in (k.fx, k.fy, k.cx, k.cy)]


@pytest.mark.slow
@needs_ycbv
def test_rgbd_files_give_the_ycbv_paths_pose(tmp_path: Path) -> None:
    """The same frame given as plain files (images, a mask PNG, intrinsics and the depth scale
    on the command line) gives the pose of `--ycbv`, bit for bit, with the mask and with best
    buddies in the box."""
    images, mask, k = _ycbv_inputs(tmp_path)
    model = str(DATA / "models" / "025_mug" / "points.xyz")
    common = ["--rgbd", *images, "--intrinsics", *k, "--depth-scale", "10000", "--model", model]
    box = (DATA / f"{FRAME}-box.txt").read_text().split("025_mug")[1].split()[:4]
    for extra, ycbv_extra in ((["--mask", mask], []),
                              (["--classifier", "best-buddies", "--box", *box],
                               ["--classifier", "best-buddies"])):
        own, ref = tmp_path / "own.json", tmp_path / "ref.json"
        # --force: the second case writes the first's files again.
        assert main(["pose", "-q", *common, *extra, "--json", str(own), "--force"]) == 0
        assert main(["pose", "-q", "--ycbv", str(DATA), "--frame", FRAME, *ycbv_extra,
                     "--json", str(ref), "--force"]) == 0
        a, b = json.loads(own.read_text()), json.loads(ref.read_text())
        assert a["T_camera_object"] == b["T_camera_object"]
        assert a["log_likelihood"] == b["log_likelihood"] and a["success"]
        assert a["errors"] is None  # no ground truth for a user's frame
        # What was posed, as given; no YCB-Video default (the mug) stands in for a name.
        assert a["input"]["rgbd"] == images and a["input"]["object"] is None
        assert a["input"]["frame"] is None and a["input"]["intrinsics"] == [float(v) for v in k]


def _tiny_frame(tmp_path: Path, *, size: tuple[int, int] = (40, 30)) -> tuple[str, str]:
    w, h = size
    color, depth = tmp_path / "c.png", tmp_path / "d.png"
    Image.fromarray(np.full((h, w, 3), 128, np.uint8)).save(color)
    Image.fromarray(np.full((h, w), 600, np.uint16)).save(depth)
    return str(color), str(depth)


@pytest.mark.parametrize("argv, message", [
    (["--intrinsics", "40", "40", "20", "15"], "--intrinsics needs --rgbd"),
    (["--mask", "m.png"], "--mask needs --rgbd"),
])
def test_rgbd_options_need_rgbd(argv: list[str], message: str, capsys) -> None:  # noqa: ANN001
    assert main(["pose", "--demo", *argv]) == 2
    assert message in capsys.readouterr().err


def test_rgbd_refuses_incomplete_or_contradictory_input(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    color, depth = _tiny_frame(tmp_path)
    pts = tmp_path / "model.xyz"
    np.savetxt(pts, np.random.default_rng(0).normal(scale=0.03, size=(200, 3)))
    mask = tmp_path / "m.png"
    Image.fromarray(np.ones((30, 40), np.uint8)).save(mask)
    base = ["pose", "--rgbd", color, depth]
    k = ["--intrinsics", "40", "40", "20", "15"]
    cases = [
        (base + ["--model", str(pts), "--mask", str(mask)], "--rgbd needs --intrinsics"),
        (base + k + ["--mask", str(mask)], "--rgbd needs one of --model POINTS and --object-model"),
        (base + k + ["--model", str(pts)], "--rgbd needs --mask MASK.png"),
        (base + k + ["--model", str(pts), "--classifier", "best-buddies"], "needs --box"),
        (base + k + ["--model", str(pts), "--mask", str(mask), "--frame", "0000/000001"],
         "--frame needs --ycbv"),
        (base + k + ["--model", str(tmp_path / "none.xyz"), "--mask", str(mask)], "does not exist"),
        (["pose", "--rgbd", color, str(tmp_path / "none.png")] + k + ["--model", str(pts),
                                                                      "--mask", str(mask)],
         "does not exist"),
        (base + k + ["--model", str(pts), "--mask", str(mask), "--depth-scale", "0"],
         "--depth-scale must be positive"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        assert message in capsys.readouterr().err, argv


def mask_ok(tmp_path: Path) -> Path:
    path = tmp_path / "mask_ok.png"
    Image.fromarray(np.ones((30, 40), np.uint8)).save(path)
    return path


def test_run_rgbd_checks_image_sizes_and_the_mask(tmp_path: Path) -> None:
    color, depth = _tiny_frame(tmp_path)
    pts = tmp_path / "model.xyz"
    np.savetxt(pts, np.random.default_rng(0).normal(scale=0.03, size=(200, 3)))
    small = tmp_path / "small.png"
    Image.fromarray(np.ones((10, 20), np.uint8)).save(small)
    empty = tmp_path / "empty.png"
    Image.fromarray(np.zeros((30, 40), np.uint8)).save(empty)
    k = (40.0, 40.0, 20.0, 15.0)
    with pytest.raises(ValueError, match=r"mask .* is 20x10 pixels, the depth image 40x30"):
        run_rgbd(color, depth, k, model_path=pts, mask_path=small)
    with pytest.raises(ValueError, match="no object pixel"):
        run_rgbd(color, depth, k, model_path=pts, mask_path=empty)
    (tmp_path / "other").mkdir()
    other_color, _ = _tiny_frame(tmp_path / "other", size=(20, 10))
    with pytest.raises(ValueError, match=r"`color` to have shape \(30, 40, 3\) to match `depth`"):
        run_rgbd(other_color, depth, k, model_path=pts, mask_path=empty)
    with pytest.raises(ValueError, match=r"`intrinsics` to be \(fx, fy, cx, cy\)"):
        run_rgbd(color, depth, (500.0, 500.0, 20.0), model_path=pts, mask_path=empty)
    with pytest.raises(ValueError, match="exactly one of `model_path`"):
        run_rgbd(color, depth, k, mask_path=empty)
    with pytest.raises(ValueError, match="exactly one of `mask_path`"):
        run_rgbd(color, depth, k, model_path=pts)
    # Depth in coarser units than the scale says (e.g. metres read as millimetres): refused,
    # not posed at a millimetre from the camera.
    coarse = tmp_path / "coarse.png"
    Image.fromarray(np.full((30, 40), 1, np.uint16)).save(coarse)
    with pytest.raises(ValueError, match=r"median depth of 1 mm: are its values metres already"):
        run_rgbd(color, coarse, k, model_path=pts, mask_path=mask_ok(tmp_path))
    Image.fromarray(np.zeros((30, 40), np.uint16)).save(coarse)
    with pytest.raises(ValueError, match="no valid"):
        run_rgbd(color, coarse, k, model_path=pts, mask_path=mask_ok(tmp_path))
    with pytest.raises(ValueError, match="fx"):
        run_rgbd(color, depth, (-500.0, 500.0, 20.0, 15.0), model_path=pts, mask_path=small)


@pytest.mark.parametrize("argv, message", [
    (["--axis", "0", "0", "1"], "--axis needs --samples N"),
    (["--samples", "10", "--axis", "0", "0", "0"], "--axis must be a non-zero finite direction"),
    (["--model-error", "3", "3"], "--model-error needs --samples N"),
    (["--samples", "10", "--model-error", "-1", "3"], "--model-error must be 'fit' or two non-negative"),
    (["--samples", "10", "--model-error", "nan", "3"], "--model-error must be 'fit' or two non-negative"),
    (["--samples", "10", "--model-error", "wide"], "--model-error must be 'fit' or two non-negative"),
    (["--samples", "10", "--model-error", "fit", "3"], "--model-error must be 'fit' or two non-negative"),
    (["--samples", "10", "--model-error", "2"], "--model-error must be 'fit' or two non-negative"),
    (["--model-error-tilt", "0.5"], "--model-error-tilt needs --samples N"),
    (["--samples", "10", "--model-error-tilt", "-1"], "--model-error-tilt must be a non-negative"),
    (["--samples", "10", "--model-error-tilt", "flat"], "--model-error-tilt must be a number of degrees or iso"),
    (["--axis-tilt-scale", "0.5"], "--axis-tilt-scale needs --samples N"),
    (["--samples", "10", "--axis-tilt-scale", "-0.5"], "--axis-tilt-scale must be a non-negative number"),
    (["--samples", "10", "--axis-tilt-scale", "inf"], "--axis-tilt-scale must be a non-negative number"),
    (["--temperature-scale", "0.5"], "--temperature-scale needs --samples N"),
    (["--samples", "10", "--temperature-scale", "0"], "--temperature-scale must be a positive number"),
    (["--samples", "10", "--temperature-scale", "nan"], "--temperature-scale must be a positive number"),
])
def test_axis_option_is_checked(argv: list[str], message: str, capsys) -> None:  # noqa: ANN001
    assert main(["pose", "--demo", *argv]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.slow
def test_axis_option_names_the_turn_the_modes_report(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """`--axis` replaces the demo's own axis: each mode line's turn is about the given one."""
    import re

    from certpose.sampling import PoseDistribution
    from certpose.sampling.plots import axis_angles

    out, js = tmp_path / "p.npz", tmp_path / "p.json"
    assert main(["pose", "--demo", "--samples", "300", "--axis", "1", "0", "0",
                 "--particles", str(out), "--json", str(js)]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("  mode 0: "))
    turn = float(re.search(r"\(([-+][\d.]+) about the axis\) from the returned pose", line).group(1))
    T = np.asarray(json.loads(js.read_text())["T_camera_object"])
    mode = PoseDistribution.load(out).modes()[0]
    assert turn == pytest.approx(np.degrees(axis_angles(mode.rotation[None], (1, 0, 0), T)[0]), abs=0.06)
    assert turn != pytest.approx(np.degrees(axis_angles(mode.rotation[None], (0, 0, 1), T)[0]), abs=0.5)


@pytest.mark.slow
def test_model_error_option_sets_the_kernel(tmp_path: Path) -> None:
    """`--model-error 0 0` gives the bare distribution, a wider kernel a wider one: the spread of
    the particles' translations (the demo's mug, 300 draws) grows with it."""
    from certpose.sampling import PoseDistribution

    spread = {}
    for deg, mm in (("0", "0"), ("10", "10")):
        out = tmp_path / f"p{deg}.npz"
        assert main(["pose", "--demo", "--samples", "300", "--particles", str(out),
                     "--model-error", deg, mm]) == 0
        d = PoseDistribution.load(out)
        spread[deg] = float(np.sqrt(np.average(np.sum((d.translations - np.average(
            d.translations, axis=0, weights=d.weights)) ** 2, axis=1), weights=d.weights)))
    assert spread["10"] > spread["0"] + 0.005, spread


@pytest.mark.slow
def test_temperature_scale_option_scales_the_sampler_temperature(tmp_path: Path) -> None:
    """`--temperature-scale S` multiplies the temperature the sampler reports (the demo's mug)."""
    temps = {}
    for scale in ("1", "0.5"):
        js = tmp_path / f"p{scale}.json"
        assert main(["pose", "--demo", "--samples", "300", "--model-error", "0", "0",
                     "--temperature-scale", scale, "--json", str(js)]) == 0
        temps[scale] = json.loads(js.read_text())["sampling"]["temperature"]
    assert temps["0.5"] == pytest.approx(0.5 * temps["1"], rel=1e-6)


@pytest.mark.slow
def test_model_error_fit_records_the_measured_misfit_and_kernel(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """`--model-error fit` scales the kernel by the depth misfit at the returned pose and writes
    both to the JSON's sampling block; the demo's renders are exact, so the misfit is below a
    millimetre and a half, and the kernel follows the rule's default gains (1, 1)."""
    js = tmp_path / "p.json"
    assert main(["pose", "--demo", "--samples", "300", "--model-error", "fit", "--json", str(js)]) == 0
    k = json.loads(js.read_text())["sampling"]["model_error"]
    assert k["rule"] == "fit" and k["dof"] == 5.0 and k["gains"] == [1.0, 1.0]
    assert 0.0 < k["misfit"] < 0.0015 and k["misfit_points"] > 300
    assert k["translation_sigma"] == pytest.approx(k["misfit"])
    assert k["rotation_sigma"] == pytest.approx(k["misfit"] / k["lever_arm"])
    assert f"model-error kernel (fit, depth misfit {1000 * k['misfit']:.2f} mm" in capsys.readouterr().out
    fixed = tmp_path / "f.json"
    assert main(["pose", "--demo", "--samples", "300", "--json", str(fixed)]) == 0
    k = json.loads(fixed.read_text())["sampling"]["model_error"]
    assert k["rule"] == "fixed" and k["rotation_sigma"] == pytest.approx(np.radians(2.0))


@pytest.mark.slow
def test_the_tilt_scale_and_the_split_kernel_are_said_and_written(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """The demo mug has an axis of revolution: by default the JSON records the tilt scale and a
    kernel with no tilt about the mug's axis, and the text says both; `--model-error-tilt iso
    --axis-tilt-scale 1` gives the isotropic kernel and no scale."""
    js = tmp_path / "p.json"
    assert main(["pose", "--demo", "--samples", "300", "--json", str(js)]) == 0
    s = json.loads(js.read_text())["sampling"]
    assert s["tilt_scale"] == 0.5
    assert s["model_error"]["tilt_sigma"] == 0.0 and abs(abs(s["model_error"]["axis"][2]) - 1.0) < 1e-3
    out = capsys.readouterr().out
    assert "tilt 0.00 deg across the axis of revolution" in out and "scaled by 0.5" in out
    iso = tmp_path / "i.json"
    assert main(["pose", "--demo", "--samples", "300", "--model-error-tilt", "iso", "--axis-tilt-scale", "1",
                 "--json", str(iso)]) == 0
    s = json.loads(iso.read_text())["sampling"]
    assert s["tilt_scale"] is None and "tilt_sigma" not in s["model_error"]
    assert "across the axis of revolution" not in capsys.readouterr().out
