"""Each user-facing example under examples/ runs and says what it should (real solvers, real files)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import DATA_DIR, require_data

ROOT = Path(__file__).resolve().parents[1]
YCBV = DATA_DIR / "ycbv"


def _run(script: str, *args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, str(ROOT / "examples" / script), *args], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=timeout)


def test_register_two_files_demo_recovers_the_pose() -> None:
    proc = _run("register_two_files.py")
    assert proc.returncode == 0, proc.stderr
    line = next(x for x in proc.stdout.splitlines() if x.startswith("error against"))
    deg = float(line.split(":")[1].split("deg")[0])
    assert deg < 2.0, proc.stdout


def test_register_two_files_reads_given_files(tmp_path: Path) -> None:
    import numpy as np

    rng = np.random.default_rng(3)
    src = rng.normal(size=(30, 3))
    np.save(tmp_path / "s.npy", src)
    np.savetxt(tmp_path / "d.csv", src + [0.5, 0.0, 0.0], delimiter=",")
    proc = _run("register_two_files.py", str(tmp_path / "s.npy"), str(tmp_path / "d.csv"),
                "--noise-bound", "0.01")
    assert proc.returncode == 0, proc.stderr
    assert "inliers: 30 of 30" in proc.stdout
    bad = _run("register_two_files.py", str(tmp_path / "s.npy"), str(tmp_path / "missing.csv"),
               "--noise-bound", "0.01")
    assert bad.returncode != 0 and "missing.csv" in bad.stderr


@pytest.mark.slow
def test_certify_example_certifies_the_pose_and_refuses_a_wrong_one() -> None:
    proc = _run("certify_pose.py", "--n", "20", "--outliers", "0.3")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "certificate of the returned pose: CERTIFIED" in proc.stdout
    assert proc.stdout.count("pose rotated by 5 deg") == 2
    assert "error: a wrong pose was certified" not in proc.stderr


@pytest.mark.slow
def test_pose_from_rgbd_demo() -> None:
    proc = _run("pose_from_rgbd.py")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "T_camera_object =" in proc.stdout and "errors against ground truth" in proc.stdout


@pytest.mark.slow
def test_pose_from_rgbd_real_frame() -> None:
    require_data("ycbv", "0000")
    proc = _run("pose_from_rgbd.py", "--ycbv", str(YCBV), "--frame", "0000/000001",
                "--object", "025_mug")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "add_s=" in proc.stdout


@pytest.mark.slow
def test_pose_from_rgbd_files_of_any_camera(tmp_path: Path) -> None:
    """The `--files` path (run_rgbd) on a YCB-Video frame given as plain files: the pose of the
    `--ycbv` path, printed without errors (no ground truth)."""
    import re

    from PIL import Image

    from certpose.io.ycbv import load_ycbv_frame

    require_data("ycbv", "0000")
    yf = load_ycbv_frame(YCBV, "0000/000001")
    mask = tmp_path / "mask.png"
    Image.fromarray(yf.object_mask("025_mug").astype(np.uint8) * 255).save(mask)
    k = yf.frame.intrinsics
    files = _run("pose_from_rgbd.py", "--files", str(YCBV / "0000/000001-color.png"),
                 str(YCBV / "0000/000001-depth.png"), "--intrinsics", *map(repr, (k.fx, k.fy, k.cx, k.cy)),
                 "--depth-scale", "10000", "--mask", str(mask),
                 "--model", str(YCBV / "models/025_mug/points.xyz"))
    ycbv = _run("pose_from_rgbd.py", "--ycbv", str(YCBV), "--frame", "0000/000001", "--object", "025_mug")
    assert files.returncode == 0 and ycbv.returncode == 0, files.stdout + files.stderr

    def pose(text: str) -> str:
        return re.search(r"T_camera_object =\n(.*?)\neq\. \(1\)", text, re.S).group(1)

    assert pose(files.stdout) == pose(ycbv.stdout)
    assert "errors against ground truth" not in files.stdout


@pytest.mark.slow
def test_pose_from_rgbd_box_only_with_views_of_another_scene() -> None:
    import re

    require_data("ycbv", "0049")
    proc = _run("pose_from_rgbd.py", "--ycbv", str(YCBV), "--frame", "0049/000001",
                "--object", "010_potted_meat_can", "--box-only", "--views", "0002/000001",
                "0002/000010")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "best buddies" in proc.stdout and "in the box" in proc.stdout
    assert float(re.search(r"add_s=([0-9.e-]+)", proc.stdout).group(1)) <= 0.01, proc.stdout
    # Views of the scene evaluated are refused.
    proc = _run("pose_from_rgbd.py", "--ycbv", str(YCBV), "--frame", "0049/000001",
                "--object", "010_potted_meat_can", "--box-only", "--views", "0049/000010")
    assert proc.returncode == 2 and "another scene" in proc.stderr


@pytest.mark.slow
def test_bench_box_on_a_real_frame(tmp_path: Path) -> None:
    require_data("ycbv", "0050")
    out = tmp_path / "box.jsonl"
    proc = _run("benchmarks/bench_box.py", "--ycbv", str(YCBV), "--models", "appearance", "--scenes", "0050",
                "--frames", "000020", "--objects", "011_banana", "--json", str(out))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    row = json.loads(out.read_text().splitlines()[0])
    assert row["case"] == "0050/000020 011_banana" and row["models"] == "appearance"
    assert row["adds_cm"] <= row["add_cm"] and 0 <= row["rot_deg"] <= 180
    assert row["positives"] > 0 and 0 <= row["precision"] <= 1
    assert "pairs 1 |" in proc.stdout and "load average" in proc.stdout
    # Item 1's setting: the mask classifier; eq. (1) of the bench's gap is the MLE's own
    # (appearance similarities scaled as in the estimate), and the refined truth is no worse
    # than the ground truth it started from.
    proc = _run("benchmarks/bench_box.py", "--ycbv", str(YCBV), "--models", "appearance", "--scenes", "0050",
                "--frames", "000020", "--objects", "011_banana", "--classifier", "mask",
                "--json", str(out))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    row = json.loads(out.read_text().splitlines()[1])
    assert row["classifier"] == "mask" and row["precision"] == 1.0
    assert row["eq1_returned"] == pytest.approx(row["log_likelihood"], abs=1e-3)
    assert row["gap"] == pytest.approx(row["eq1_returned"] - row["eq1_truth_refined"])
    # The gap's parts (classifier and free space, shape, colour on seen and unseen points) sum
    # to it, and a model with appearance has colour on both kinds of points.
    terms = row["gap_terms"]
    assert set(terms) == {"classifier_free_space", "shape", "colour_seen", "colour_unseen"}
    assert sum(terms.values()) == pytest.approx(row["gap"], abs=1e-3)
    assert isinstance(row["flip"], bool) and "flips" in proc.stdout


@pytest.mark.slow
def test_bench_dense_quick(tmp_path: Path) -> None:
    require_data("3dmatch", "gt.npy")
    require_data("bunny", "bun_zipper_res3.ply")
    out = tmp_path / "dense.json"
    proc = _run("benchmarks/bench_dense.py", "--quick", "--json", str(out))
    assert proc.returncode == 0, proc.stderr
    report = json.loads(out.read_text())
    m = report["3dmatch"]
    assert m["success"] and m["graph_edges"] > 10_000, m
    graphs = report["graphs"]
    assert graphs["dense 0.9"]["median_edges"] > 10 * graphs["sparse 0.9"]["median_edges"]
    assert graphs["dense 0.9"]["success_rate"] == 1.0
    assert set(report["bunny_n100"]) == {"0", "0.5", "0.8", "0.9", "0.95"}
    assert "load average" in proc.stdout


@pytest.mark.slow
def test_distribution_to_samplers_example() -> None:
    """The demo's pose distribution starts emcee, PyMC, a gtsam graph and Nevergrad (all real)."""
    proc = _run("distribution_to_samplers.py", "--samples", "500", "--steps", "10",
                "--de-budget", "500")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = {x.split(":")[0]: x for x in proc.stdout.splitlines()}
    assert "chain shape (10, 32, 6)" in lines["emcee"]
    cm = float(lines["emcee"].split("final walkers ")[1].split(" cm")[0])
    assert cm < 1.0, proc.stdout  # the walkers stay on the mug
    cm = float(lines["pymc"].split("draws ")[-1].split(" cm")[0])
    assert cm < 1.0, proc.stdout  # the chains stay on the mug
    assert "x1 2.00 cm away" in lines["gtsam"]
    assert "500 evaluations from 32 suggested poses" in lines["nevergrad"]


@pytest.mark.slow
def test_bench_samplers_demo(tmp_path: Path) -> None:
    """The side-by-side benchmark: three methods, one target, one wall-clock budget."""
    import json
    import math

    out = tmp_path / "bench.json"
    png = tmp_path / "marginals.png"
    proc = _run("benchmarks/bench_samplers.py", "--no-ycbv", "--json", str(out), "--target-draws", "20000",
                "--plot", str(png))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = json.loads(out.read_text())["rows"]
    assert [r["method"] for r in rows] == ["IS (ours)", "Nevergrad DE", "MCMC (RWM)"]
    assert len({r["temperature"] for r in rows}) == 1
    budget = rows[0]["seconds"]
    for r in rows:
        assert r["ess"] > 0 and math.isfinite(r["log_p_gt"]) and 0 <= r["arc_coverage"] <= 1
        assert 0 <= r["arc_coverage_in_arc"] <= 1 and math.isfinite(r["log_p_gt_target"])
        assert 0 <= r["union_coverage"] <= 1 and r["mass_in_union"] >= r["mass_in_arc"]
        assert r["log_p_gt_error"] == abs(r["log_p_gt"] - r["log_p_gt_target"])
        # The baselines stop at ours' sampling time (plus at most one batch of evaluations).
        assert r["seconds"] <= budget + 1.0, r
        assert 0 <= r["tv_target"] <= 1 and 0 <= r["outside_target"] <= 1 and 0 < r["target_mass_in_arc"] <= 1
    # Against the target's own marginal about the axis, ours is closer than DE (0.04 vs 0.4-0.9).
    assert rows[0]["tv_target"] < rows[1]["tv_target"], rows
    assert "ours best or tied on" in proc.stdout and "from the target's exact marginal" in proc.stdout
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


@pytest.mark.slow  # four bench processes, two of them with a Dask cluster
def test_bench_dask_scaling_example() -> None:
    proc = _run("benchmarks/bench_dask_scaling.py", "--instances", "10", "20", "--workers", "0", "1",
                "--solvers", "gnc-only", "--synthetic")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = [line.split() for line in proc.stdout.splitlines() if line[:9].strip().isdigit()]
    assert [(r[0], r[1], r[2]) for r in rows] == [("10", "0", "10"), ("10", "1", "10"),
                                                 ("20", "0", "20"), ("20", "1", "20")]
    assert all(float(r[-1]) > 10 for r in rows)  # a driver's peak RSS in MiB
    assert all(float(r[5]) > 0 for r in rows)  # the CPU time of the run's processes
    assert "load average" in proc.stdout


@pytest.mark.slow
def test_bench_basins_on_a_real_frame(tmp_path: Path) -> None:
    require_data("ycbv", "0000")
    out = tmp_path / "basins.jsonl"
    proc = _run("benchmarks/bench_basins.py", "--ycbv", str(YCBV), "--scenes", "0000", "--frames",
                "000003", "--objects", "025_mug", "--json", str(out))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    row = json.loads(out.read_text().splitlines()[0])
    assert row["case"] == "0000/000003 025_mug"
    # The truth refined on eq. (1) scores at least as well as the truth itself, and stays close.
    assert row["eq1_truth_refined"] >= row["eq1_truth"] - 1e-6
    assert row["refined_truth_adds_cm"] < 1.0
    assert row["gap"] == pytest.approx(row["eq1_returned"] - row["eq1_truth_refined"])
    # The reported modes include the returned pose: the one nearest the truth is no farther.
    assert row["modes"] >= 1 and row["truth_mode_rot_deg"] <= row["rot_deg"] + 1e-9
    assert row["truth_in_modes"] == (row["truth_mode_rot_deg"] <= 10.0
                                     and row["truth_mode_adds_cm"] <= 1.0)
    assert "pairs 1 |" in proc.stdout and "truth among the reported modes" in proc.stdout


@pytest.mark.slow
def test_bench_calibration_on_a_real_pair(tmp_path: Path) -> None:
    require_data("ycbv", "0000")
    args = ["--data", str(YCBV), "--scenes", "0000", "--frames", "000003", "--objects", "025_mug",
            "--cache", str(tmp_path / "cache"), "--draws", "1000"]
    proc = _run("benchmarks/bench_calibration.py", *args, "--out", str(tmp_path / "is.jsonl"))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    row = json.loads((tmp_path / "is.jsonl").read_text().splitlines()[0])
    assert row["case"] == "0000/000003 025_mug" and row["model"] == "geometry"
    assert 0.0 <= row["levels"]["x1"] <= 1.0 and 0.0 <= row["kde_levels"]["x1"] <= 1.0
    assert row["ess"]["x1"] > 50
    # The truth refined on eq. (1) is at least as good as the truth.
    assert row["eq1_truth_refined"] >= row["eq1_truth"] - 1e-6
    assert len(list((tmp_path / "cache").glob("*.pkl"))) == 1
    # The calibrated distribution on the cached MLE (no second MLE: the cached row comes back).
    proc = _run("benchmarks/bench_calibration.py", *args, "--calibrated", "--out", str(tmp_path / "cal.jsonl"))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    cal = json.loads((tmp_path / "cal.jsonl").read_text().splitlines()[0])
    assert cal["mle_s"] == row["mle_s"] and cal["num_basins"] >= 1
    assert 0.0 <= cal["levels"]["default"] <= 1.0
    assert "calibrated distribution (defaults)" in proc.stdout


@pytest.mark.slow
def test_bench_eq2_on_a_real_frame(tmp_path: Path) -> None:
    require_data("ycbv", "0002")
    out = tmp_path / "eq2.jsonl"
    proc = _run("benchmarks/bench_eq2.py", "--ycbv", str(YCBV), "--scenes", "0002", "--frames", "000001",
                "--objects", "006_mustard_bottle", "--num-object-points", "100", "--top-k", "40",
                "--num-seeds", "0", "--json", str(out))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    row = json.loads(out.read_text().splitlines()[0])
    assert row["case"] == "0002/000001 006_mustard_bottle"
    # The wide eq. (2): 100 object points x top-40, some of them right at the true pose.
    assert row["N"] == 4000
    assert 0 < row["points"] <= row["inliers"] <= row["N"]
    assert row["adds_cm"] > 0 and 0 <= row["rot_deg"] <= 180
    assert row["solve_ms"] > 0 and row["certify_ms"] > 0
    assert isinstance(row["eq2_wins"], bool) and row["hypothesis"]
    assert "pairs 1 |" in proc.stdout and "load average" in proc.stdout


@pytest.mark.slow
def test_bench_target_arc_on_the_demo(tmp_path: Path) -> None:
    """The target's own right-ambiguity figures (no sampler) on the demo, whose arc is exact."""
    out = tmp_path / "target.json"
    proc = _run("benchmarks/bench_target_arc.py", "--no-ycbv", "--draws", "20000", "--json", str(out))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (row,) = json.loads(out.read_text())["rows"]
    assert row["scene"] == "demo" and 5.0 < row["temperature"] < 20.0, row
    # Measured (seed 0, 60,000 draws): 0.90 of the target's mass in the rendered
    # arc (eq. (1) flat 10-15 deg past its far end), every bin covered, the axis 0.99 right.
    assert 0.8 < row["in_arc"] <= row["in_union"] <= 1.0 and row["union_coverage"] == 1.0, row
    assert row["axis_ok"] > 0.9 and row["tv_error"] < 0.06, row
    assert "demo " in proc.stdout and "no / no" in proc.stdout


@pytest.mark.slow
def test_bench_arc_reports_the_ratio_per_frame_and_part(tmp_path: Path) -> None:
    require_data("ycbv", "0000")
    png, dump = tmp_path / "arc.png", tmp_path / "arc.json"
    proc = _run("benchmarks/bench_arc.py", "--frames", "000001", "--step", "10", "--no-refine",  # defaults
                "--plot", str(png), "--json", str(dump))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    from PIL import Image

    with Image.open(png) as im:  # one panel per frame
        assert im.format == "PNG" and im.size[0] > im.size[1] > 100, im.size
    assert "likelihood overrides none" in proc.stdout
    # The computed arc (the free-space definition) holds the ground truth and about the stated
    # -15..80 deg; the other free runs are printed with it.
    line = next(x for x in proc.stdout.splitlines() if x.startswith("000001: free-space arc"))
    lo, hi = (float(v) for v in line.split("grid) ")[1].split(" deg")[0].split(".."))
    assert -40 < lo < -10 and 60 < hi < 110, line
    assert "other free runs" in line
    rows = [x.split() for x in proc.stdout.splitlines() if x.startswith("000001 ")]
    parts = {(r[1], r[2] if r[2] != "eq." else "eq1"): r for r in rows}
    assert {(a, p) for a in ("computed", "stated")
            for p in ("eq1", "body", "handle", "body.desc", "body.free", "body.cls")} <= set(parts), proc.stdout
    # The body's split per term (descriptor similarity, free-space charge, classifier) adds up
    # to its share; the similarity and the classifier's term both vary along the circle.
    frame = json.loads(dump.read_text())["frames"][0]
    split = np.asarray(frame["body_parts"])
    np.testing.assert_allclose(split.sum(axis=1), frame["body"], rtol=0, atol=1e-6)
    assert np.ptp(split[:, 0]) > 1.0 and np.ptp(split[:, 2]) > 1.0, split
    assert "computed arc: eq. (1) ratio over 1 frames" in proc.stdout
    assert "stated arc: eq. (1) ratio over 1 frames" in proc.stdout
    # On the stated arc the handle is hidden inside most of it and emerges outside: its share
    # drops outside by more than twice its range inside, and so does eq. (1).
    rng_in, drop = (float(x) for x in parts[("stated", "handle")][-4:-2])
    assert drop > 2 * rng_in, proc.stdout
    rng_in, drop = (float(x) for x in parts[("stated", "eq1")][-4:-2])
    assert drop > 2 * rng_in, proc.stdout


@pytest.mark.slow
def test_bench_arc_with_the_per_pixel_free_space() -> None:
    require_data("ycbv", "0000")
    proc = _run("benchmarks/bench_arc.py", "--frames", "000001", "--step", "10", "--no-refine",
                "--free-space", "pixels", "--arc-free-space", "pixels", "--arc-max-violations", "10")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "'free_space': 'pixels'" in proc.stdout
    # The per-pixel arc holds the ground truth, about the stated -15..80 deg.
    line = next(x for x in proc.stdout.splitlines() if x.startswith("000001: free-space arc"))
    lo, hi = (float(v) for v in line.split("grid) ")[1].split(" deg")[0].split(".."))
    assert -40 < lo < -10 and 60 < hi < 110, line
    rows = [x.split() for x in proc.stdout.splitlines() if x.startswith("000001 ")]
    parts = {(r[1], r[2] if r[2] != "eq." else "eq1"): r for r in rows}
    # Unrefined, the handle's share is charged outside the arc and (nearly) flat inside it.
    rng_in, drop = (float(x) for x in parts[("computed", "handle")][-4:-2])
    assert drop > rng_in > 0, proc.stdout


@pytest.mark.slow
def test_bench_pose_calls_times_both_ways_and_checks_the_poses_agree() -> None:
    require_data("ycbv", "0000")
    proc = _run("benchmarks/bench_pose_calls.py", "--scenes", "0000", "--objects", "2")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "2 pairs in 1 frames" in proc.stdout
    one = [x for x in proc.stdout.splitlines() if " one call " in x]
    assert len(one) == 2 and all(float(x.split()[-2]) > 0 for x in one), proc.stdout
    assert "one process" in proc.stdout
    line = next(x for x in proc.stdout.splitlines() if x.startswith("largest difference"))
    assert float(line.split(":")[1].split(";")[0]) <= 1e-9, line


@pytest.mark.slow
def test_bench_mle_times_each_pair_warm_and_by_stage(tmp_path: Path) -> None:
    require_data("ycbv", "0000")
    out = tmp_path / "mle.json"
    proc = _run("benchmarks/bench_mle.py", "--scenes", "0000", "--objects", "009_gelatin_box",
                "--rounds", "2", "--json", str(out))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "1 pairs built" in proc.stdout
    row = next(x for x in proc.stdout.splitlines() if x.startswith("0000/000001 009_gelatin_box"))
    wall, *stages, other, cpu = (float(v) for v in row.split()[2:])
    assert wall > 0 and cpu > 0 and len(stages) == 7 and sum(stages) <= wall + 1e-6, row
    records = json.loads(out.read_text())
    assert [r["round"] for r in records] == [0, 1]  # the warm-up, then the timed round
    # The same seed, the same pose both rounds; the returned pose is the first mode.
    np.testing.assert_array_equal(records[0]["T_scene_object"], records[1]["T_scene_object"])
    assert records[1]["modes"][0]["T_scene_object"] == records[1]["T_scene_object"]
    assert records[1]["timings"]["total"] <= records[1]["seconds"]
    assert "median" in proc.stdout and "load average" in proc.stdout


@pytest.mark.slow
def test_object_model_from_views_builds_from_a_manifest_and_poses(tmp_path: Path) -> None:
    """Posed renders written as a manifest, the model built from it, the mug posed with it."""
    proc = _run("object_model_from_views.py")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "seen by 4 views" in proc.stdout
    line = next(x for x in proc.stdout.splitlines() if x.startswith("pose:"))
    axis = float(line.split("symmetry axis ")[1].split(" deg")[0])
    adds = float(line.split("ADD-S ")[1].split(" cm")[0])
    assert axis < 5.0 and adds < 1.0, line
    # Your own manifest: the model is saved and loads back.
    import json

    from certpose.geometry.appearance import BuiltObjectModel

    sys.path.insert(0, str(ROOT / "examples"))
    from object_model_from_views import write_manifest

    manifest, points = write_manifest(tmp_path)
    np.savetxt(tmp_path / "mug.xyz", points)
    out = tmp_path / "mug.npz"
    proc = _run("object_model_from_views.py", "--manifest", str(manifest), "--model",
                str(tmp_path / "mug.xyz"), "-o", str(out))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert len(json.loads(manifest.read_text())["views"]) == 4
    assert len(BuiltObjectModel.load(out).views) == 4


@pytest.mark.slow
def test_bench_run_example_puts_certpose_and_peers_side_by_side() -> None:
    proc = _run("bench_run.py", "--trials", "2", "--outlier-ratios", "0.5",
                "--solvers", "gnc", "gnc+certify", "o3d-fgr")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = {x.split()[1]: x.split() for x in proc.stdout.splitlines() if x.startswith("synthetic")}
    assert set(rows) == {"gnc", "gnc+certify", "o3d-fgr"}
    assert float(rows["gnc"][4]) == 100.0 and float(rows["gnc+certify"][10]) == 100.0, proc.stdout
    assert "6 rows in" in proc.stdout


SCRIPTS = sorted(p.relative_to(ROOT / "examples").as_posix()
                 for p in (ROOT / "examples").rglob("*.py"))


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_example_and_benchmark_has_a_working_help(script: str) -> None:
    proc = _run(script, "--help", timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.startswith("usage:"), proc.stdout


def test_examples_keep_one_script_per_use_and_benchmarks_apart() -> None:
    top = sorted(p.name for p in (ROOT / "examples").glob("*.py"))
    assert top == ["bench_run.py", "certify_pose.py", "distribution_to_samplers.py",
                   "object_model_from_views.py", "pose_from_rgbd.py", "register_two_files.py"]
    listed = (ROOT / "examples" / "benchmarks" / "README.md").read_text()
    for p in (ROOT / "examples" / "benchmarks").glob("*.py"):
        assert f"`{p.name}`" in listed, p.name


def test_paths_the_docs_name_exist() -> None:
    """Every examples/... script the README, the docs and the examples name is there."""
    import re

    texts = [ROOT / "README.md", *(ROOT / "docs").rglob("*.md"), *(ROOT / "examples").rglob("*.py"),
             *(ROOT / "examples").rglob("*.md")]
    for path in texts:
        for name in re.findall(r"examples/[A-Za-z0-9_/]+\.py", path.read_text()):
            assert (ROOT / name).is_file(), f"{path.relative_to(ROOT)} names {name}"
def test_bench_certify_scans_certifies_a_statement_about_the_returned_pose() -> None:
    """At 0.1 m the default call certifies the rotation subproblem, or the full problem for a
    pose no costlier than the solver's when its search finishes in the time limit."""
    data = require_data("3dmatch", "gt.npy").parent
    proc = _run("benchmarks/bench_certify_scans.py", "--data", str(data), "--noise-bounds", "0.1")
    assert proc.returncode == 0, proc.stderr
    rows = [line.split() for line in proc.stdout.splitlines() if line.startswith(" 0.10")]
    by_prefer = {r[1]: r for r in rows}
    cert = by_prefer["certificate"]
    assert cert[3] == "True" and cert[4] in ("rotation_tim_subproblem", "full_weighted_tls")
    if cert[4] == "full_weighted_tls":
        assert float(cert[6]) <= float(cert[7])
    assert float(by_prefer["cost"][6]) <= float(by_prefer["cost"][7])  # never costlier
    assert "load" in proc.stdout


def test_bench_certify_scans_runs_pairs_of_cloud_files() -> None:
    """``--pair SRC TGT [GT]``: the shared pair's own files, once with its ground truth (rotation
    errors printed, small) and once without (``-`` in their place)."""
    data = require_data("3dmatch", "gt.npy").parent
    src, ref, gt = (str(data / f) for f in ("src.npy", "ref.npy", "gt.npy"))
    proc = _run("benchmarks/bench_certify_scans.py", "--no-shared", "--pair", src, ref, gt,
                "--pair", src, ref, "--noise-bounds", "0.1", "--time-limit", "1")
    assert proc.returncode == 0, proc.stderr
    cases = proc.stdout.split("== src.npy -> ref.npy: ")[1:]
    assert len(cases) == 2 and "shared 3DMatch pair" not in proc.stdout
    with_gt, without = ([line.split() for line in c.splitlines() if line.startswith(" 0.10")]
                        for c in cases)
    assert "ground truth given" in cases[0] and "ground truth none" in cases[1]
    assert len(with_gt) == len(without) == 2
    assert all(float(r[8]) < 5 and float(r[9]) < 5 for r in with_gt), cases[0]
    assert all(r[8] == r[9] == "-" for r in without), cases[1]
    bad = _run("benchmarks/bench_certify_scans.py", "--no-shared", "--pair", src)
    assert bad.returncode == 2 and "--pair takes SRC TGT [GT]" in bad.stderr
