"""BOP pose runs: the results files, resume, the same poses as `pose --ycbv`, Dask and SIGKILL."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from certpose.bop.results import (
    BOP_COLUMNS,
    SIDE_COLUMNS,
    bop_row_cells,
    open_results,
    read_bop_results,
    side_path,
)
from tests.conftest import require_data

ROOT = Path(__file__).resolve().parents[1]


def test_bop_cells_row_major_in_millimetres(tmp_path):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -1.2, 0.4]).as_matrix()
    T[:3, 3] = [0.0123, -0.5, 1.25]
    R, t = bop_row_cells(T)
    assert [float(v) for v in R.split()] == list(T[:3, :3].ravel())  # row-major, exact
    assert [float(v) for v in t.split()] == pytest.approx([12.3, -500.0, 1250.0], abs=1e-12)
    path = tmp_path / "r.csv"
    path.write_text(",".join(BOP_COLUMNS) + f"\n3,7,14,0.5,{R},{t},1.5\n")
    (row,) = read_bop_results(path)
    assert (row["scene_id"], row["im_id"], row["obj_id"]) == (3, 7, 14)
    np.testing.assert_array_equal(row["R"], T[:3, :3])
    np.testing.assert_allclose(row["t"], T[:3, 3], rtol=1e-15)
    path.write_text("scene_id,im_id\n1,2\n")
    with pytest.raises(ValueError, match="not a BOP results file"):
        read_bop_results(path)


def _write(path: Path, columns, rows, tail: str = "") -> None:
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(columns), lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
        fh.write(tail)


def test_resume_keeps_complete_images_only(tmp_path):
    res = tmp_path / "r.csv"
    expected = {(0, 1): 2, (0, 2): 2, (0, 3): 1}

    def side(im, obj, ok=True):
        return {"scene_id": 0, "im_id": im, "obj_id": obj, "gt_id": 0, "success": ok}

    def bop(im, obj):
        return {"scene_id": 0, "im_id": im, "obj_id": obj, "score": 1, "R": "1 0 0 0 1 0 0 0 1",
                "t": "0 0 500", "time": 2.0}

    # Image 1 complete (one failure: no BOP row); image 2 killed after its first side row;
    # image 3's side row written but not its BOP row; a half line at the end.
    _write(side_path(res), SIDE_COLUMNS,
           [side(1, 5), side(1, 6, ok=False), side(2, 5), side(3, 7)], tail="0,2,6,1,Tr")
    _write(res, BOP_COLUMNS, [bop(1, 5)])
    with pytest.raises(FileExistsError):
        open_results(res, expected)
    b, s, done = open_results(res, expected, resume=True)
    b.close()
    s.close()
    assert done == {(0, 1)}
    assert [r["im_id"] for r in read_bop_results(res)] == [1]
    with side_path(res).open() as fh:
        assert [(r["im_id"], r["obj_id"]) for r in csv.DictReader(fh)] == [("1", "5"), ("1", "6")]
    assert side_path(res).read_text().endswith("\n")
    # Killed before a header was written: the resumed files get theirs.
    res.write_text("")
    side_path(res).write_text("")
    b, s, done = open_results(res, expected, resume=True)
    b.close()
    s.close()
    assert done == set() and read_bop_results(res) == []
    assert side_path(res).read_text() == ",".join(SIDE_COLUMNS) + "\n"
    _write(side_path(res), SIDE_COLUMNS, [side(1, 5), side(1, 6, ok=False)])
    _write(res, BOP_COLUMNS, [bop(1, 5)])
    # A side file with more rows for an image than its targets is another run's.
    with pytest.raises(ValueError, match="holds 2 rows"):
        open_results(res, {(0, 1): 1}, resume=True)


@pytest.fixture(scope="module")
def bop_ycbv(tmp_path_factory):
    from certpose.bop.convert import convert_ycbv

    root = require_data("ycbv")
    out = tmp_path_factory.mktemp("bop") / "ycbv"
    convert_ycbv(root, out, frames=["0000/000001", "0000/000002", "0000/000003",
                                    "0049/000010"])
    return root, out


def _env(tmp_cache: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _cmd(ds: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "certpose", "pose", "--bop", str(ds), "--out", str(out), "-q",
            *extra]


@pytest.mark.slow
def test_same_poses_as_pose_ycbv_pair_by_pair(bop_ycbv, tmp_path):
    """Every row equals `run_ycbv` (what `certpose pose --ycbv` runs) on the same pair."""
    from certpose.cli import main
    from certpose.estimation.pipeline import run_ycbv
    from certpose.io.bop import load_bop_targets

    root, ds = bop_ycbv
    targets = load_bop_targets(ds / "test_targets_bop19.json")
    out = tmp_path / "r.csv"
    assert main(["pose", "--bop", str(ds), "--out", str(out), "--workers", "0", "-q"]) == 0
    rows = {(r["scene_id"], r["im_id"], r["obj_id"]): r for r in read_bop_results(out)}
    assert len(rows) == len(targets) == 13
    names = (root / "models" / "classes.txt").read_text().split()
    for t in targets:
        ref = run_ycbv(root, f"{t.scene_id:04d}/{t.im_id:06d}", names[t.obj_id - 1], rng=0)
        r = rows[(t.scene_id, t.im_id, t.obj_id)]
        np.testing.assert_allclose(r["R"], ref.T_camera_object[:3, :3], rtol=0, atol=1e-9)
        np.testing.assert_allclose(r["t"], ref.T_camera_object[:3, 3], rtol=0, atol=1e-9)


def _rows_without_time(path: Path, drop: tuple[str, ...]) -> list[tuple[str, ...]]:
    with path.open(newline="") as fh:
        return [tuple(v for k, v in r.items() if k not in drop) for r in csv.DictReader(fh)]


@pytest.mark.slow
def test_sigkill_and_resume_equal_an_uninterrupted_run(bop_ycbv, tmp_path):
    """A real 2-worker LocalCluster run killed with SIGKILL mid-run, resumed: the same rows as an
    uninterrupted run (all but the timings), none lost, none twice."""
    pytest.importorskip("distributed")
    _, ds = bop_ycbv
    env = _env(tmp_path)
    full = tmp_path / "full.csv"
    subprocess.run(_cmd(ds, full, "--workers", "2"), check=True, env=env, timeout=600)
    killed = tmp_path / "killed.csv"
    proc = subprocess.Popen(_cmd(ds, killed, "--workers", "2"), env=env, start_new_session=True)
    try:
        side = side_path(killed)
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None:
            if side.exists() and side.read_text().count("\n") >= 2:  # header + a first image
                break
            time.sleep(0.05)
        assert proc.poll() is None, "the run ended before it could be killed"
        os.killpg(proc.pid, signal.SIGKILL)  # the driver, its scheduler and the workers
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    n_before = side.read_text().count("\n") - 1
    assert 1 <= n_before < 13
    with pytest.raises(subprocess.CalledProcessError):  # never overwritten silently
        subprocess.run(_cmd(ds, killed, "--workers", "2"), check=True, env=env, timeout=600,
                       stderr=subprocess.DEVNULL)
    proc = subprocess.run(_cmd(ds, killed, "--workers", "2", "--resume", "--json", "-"),
                          check=True, env=env, timeout=600, capture_output=True, text=True)
    summary = json.loads(proc.stdout)
    assert summary["skipped_images"] >= 1 and summary["posed"] < 13
    assert _rows_without_time(killed, ("time",)) == _rows_without_time(full, ("time",))
    assert (_rows_without_time(side_path(killed), ("seconds",))
            == _rows_without_time(side_path(full), ("seconds",)))
    assert len(read_bop_results(killed)) == 13


def test_cli_refuses_bad_bop_options(bop_ycbv, tmp_path, capsys):
    from certpose.cli import main

    _, ds = bop_ycbv
    out = tmp_path / "r.csv"
    assert main(["pose", "--bop", str(ds), "-q"]) == 2  # no --out
    assert main(["pose", "--bop", str(ds), "--out", str(out), "--object", "025_mug", "-q"]) == 2
    assert main(["pose", "--demo", "--out", str(out), "-q"]) == 2
    capsys.readouterr()
    assert main(["pose", "--bop", str(ds), "--out", str(out), "--certify-modes", "-q"]) == 2
    assert "--certify-modes" in capsys.readouterr().err
    assert main(["pose", "--bop", str(ds), "--out", str(out), "--workers", "1",
                 "--scheduler", "tcp://x:1", "-q"]) == 2
    out.write_text("x")
    assert main(["pose", "--bop", str(ds), "--out", str(out), "-q"]) == 2  # exists
    assert out.read_text() == "x"


def _one_image_targets(ds: Path, tmp_path: Path) -> Path:
    t = [{"scene_id": 49, "im_id": 10, "obj_id": 13, "inst_count": 1},
         {"scene_id": 49, "im_id": 10, "obj_id": 9, "inst_count": 1}]
    path = tmp_path / "targets.json"
    path.write_text(json.dumps(t))
    return path


@pytest.mark.slow
def test_running_scheduler_and_particles(bop_ycbv, tmp_path):
    """--scheduler ADDRESS of a running cluster gives the in-process rows; --samples with
    --particles-dir writes each target's particles and the side file's ESS."""
    distributed = pytest.importorskip("distributed")
    from certpose.cli import main

    _, ds = bop_ycbv
    targets = _one_image_targets(ds, tmp_path)
    here = tmp_path / "here.csv"
    assert main(["pose", "--bop", str(ds), "--targets", str(targets), "--out", str(here),
                 "--workers", "0", "-q"]) == 0
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        there = tmp_path / "there.csv"
        subprocess.run(_cmd(ds, there, "--targets", str(targets), "--scheduler",
                            cluster.scheduler_address), check=True, env=_env(tmp_path),
                       timeout=600)
    assert _rows_without_time(here, ("time",)) == _rows_without_time(there, ("time",))
    pdir = tmp_path / "particles"
    pdir.mkdir()
    out = tmp_path / "sampled.csv"
    assert main(["pose", "--bop", str(ds), "--targets", str(targets), "--out", str(out),
                 "--workers", "0", "--samples", "300", "--particles-dir", str(pdir), "-q"]) == 0
    with side_path(out).open(newline="") as fh:
        side = list(csv.DictReader(fh))
    assert [r["particles"] for r in side] == ["000049_000010_000009_000002.npz",
                                              "000049_000010_000013_000003.npz"]
    for r in side:
        assert float(r["ess"]) > 0
        with np.load(pdir / r["particles"]) as d:
            assert len(d["weights"]) == 300


def test_object_build_bop_fills_the_cache(bop_ycbv, tmp_path, monkeypatch):
    from certpose.cli import main

    _, ds = bop_ycbv
    monkeypatch.setenv("CERTPOSE_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "b.json"
    assert main(["object", "build", "--bop", str(ds), "--objects", "14", "--json", str(out),
                 "-q"]) == 0
    assert [o["obj_id"] for o in json.loads(out.read_text())["objects"]] == [14]
    assert len(list((tmp_path / "cache" / "objects").glob("*.npz"))) == 1
    # The mug's visibility table too: the workers of a run read it instead of casting rays.
    assert len(list((tmp_path / "cache" / "derived").glob("visibility-*.npz"))) == 1
    assert main(["object", "build", "--bop", str(ds), "--objects", "99", "-q"]) == 2
    assert main(["object", "build", "--bop", str(ds), "-o", "x.npz", "-q"]) == 2
