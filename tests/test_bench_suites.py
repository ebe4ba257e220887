"""``certpose bench`` suites and reports: a folder of problem files, the 3DMatch pair, eq. (2)
problems, --report redrawn from saved rows, and one-line errors (exit 2) on malformed grids,
problem files and result files."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from certpose.bench.rows import TRIAL_COLUMNS
from certpose.bench.runner import BenchConfig, run_benchmark
from certpose.cli import main
from certpose.data.instances import make_instance
from certpose.io.points import synthetic_shape
from certpose.io.problems import save_problem
from tests.conftest import require_data, strict_json

TIMES = ["time_ms", "reported_time_ms"]


def _folder(tmp_path: Path) -> Path:
    """Three problems with ground truth (0%, 50%, 80% outliers) and one without."""
    folder = tmp_path / "mine"
    (folder / "sub").mkdir(parents=True)
    shape = synthetic_shape()
    for k, ratio in enumerate((0.0, 0.5, 0.8)):
        inst = make_instance(shape, 40, ratio, noise=0.01, rng=k)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = inst.rotation, inst.translation
        save_problem(folder / f"p{k}.npz", inst.source, inst.target,
                     noise_bound=inst.noise_bound, T_target_source=T)
    inst = make_instance(shape, 30, 0.3, noise=0.01, rng=9)
    save_problem(folder / "sub" / "no_gt.npz", inst.source, inst.target,
                 noise_bound=np.full(30, inst.noise_bound), weights=np.full(30, 2.0))
    return folder


def test_problems_dir_bench_rows_and_resume(tmp_path, capsys):
    folder = _folder(tmp_path)
    out = tmp_path / "res"
    assert main(["bench", "--problems", str(folder), "--solvers", "gnc", "o3d-fgr",
                 "--workers", "0", "--out", str(out), "--no-progress"]) == 0
    df = pd.read_csv(out / "trials.csv")
    assert list(df.columns) == list(TRIAL_COLUMNS) and len(df) == 4 * 2
    assert set(df["suite"]) == {"mine"}
    assert set(df["instance"]) == {"p0.npz", "p1.npz", "p2.npz", "sub/no_gt.npz"}
    gnc = df[df.solver == "gnc"].set_index("instance")
    # Outlier ratios come from the ground truth; errors and success against it.
    assert gnc.loc["p1.npz", "outlier_ratio"] == pytest.approx(0.5)
    assert gnc.loc[["p0.npz", "p1.npz", "p2.npz"], "success"].all()
    assert (gnc.loc[["p0.npz", "p1.npz", "p2.npz"], "rotation_error_deg"] < 5).all()
    # Without ground truth: no errors, success is the solver's verdict; the cost is the
    # weighted TLS cost (weights 2: twice the unweighted one).
    assert math.isnan(gnc.loc["sub/no_gt.npz", "rotation_error_deg"])
    assert gnc.loc["sub/no_gt.npz", "success"]
    assert gnc.loc["sub/no_gt.npz", "cost"] > 0
    assert df["error"].isna().all()
    stdout = capsys.readouterr().out
    assert "mine" in stdout and "gnc" in stdout and "o3d-fgr" in stdout

    # Killed after three rows and resumed: the rows of the whole run.
    path = out / "trials.csv"
    whole = path.read_text()
    lines = whole.splitlines(keepends=True)
    path.write_text("".join(lines[:4]) + lines[4][:10])
    assert main(["bench", "--problems", str(folder), "--solvers", "gnc", "o3d-fgr",
                 "--workers", "0", "--out", str(out), "--no-progress", "--resume"]) == 0

    def canon(text_path: Path) -> pd.DataFrame:
        d = pd.read_csv(text_path, keep_default_na=False, dtype=str).drop(columns=TIMES)
        return d.sort_values(["suite", "instance", "solver"]).reset_index(drop=True)

    (tmp_path / "whole.csv").write_text(whole)
    assert canon(path).equals(canon(tmp_path / "whole.csv"))


@pytest.mark.slow  # the certifier's first run (imports, JIT) and two plots: about 4.5 s
def test_report_redraws_from_saved_rows(tmp_path, capsys):
    out = tmp_path / "res"
    assert main(["bench", "--n", "12", "--outlier-ratios", "0", "0.25", "--trials", "2",
                 "--solvers", "gnc", "gnc+certify", "--workers", "0", "--out", str(out),
                 "--no-progress", "--plot"]) == 0
    first = capsys.readouterr().out
    summary = (out / "summary.csv").read_text()
    for name in ("summary.csv", "bench.json", "bench.png", "certificates.png", "report.md"):
        (out / name).unlink()
    saved = (out / "trials.csv").read_text()

    assert main(["bench", "--report", str(out), "--json", "-"]) == 0
    captured = capsys.readouterr()
    data = strict_json(captured.out)  # only JSON on stdout with --json -
    assert (out / "trials.csv").read_text() == saved  # nothing solved, nothing appended
    assert (out / "summary.csv").read_text() == summary
    assert {r["solver"] for r in data["summary"]} == {"gnc", "gnc+certify"}
    assert data["certificates"][0]["cert_problem"] == "full_weighted_tls"
    import imageio.v3 as iio

    for png in ("bench.png", "certificates.png"):
        img = iio.imread(out / png)
        assert img.ndim == 3 and img.shape[0] > 100 and img.std() > 0
    md = (out / "report.md").read_text()
    assert md.startswith("# certpose bench report")
    assert "| gnc+certify | 12 | 0.25 | 2 | 100% |" in md
    assert "full_weighted_tls" in md and "![bench](bench.png)" in md
    assert "load average" in md
    # The terminal table of the redraw is the run's.
    assert main(["bench", "--report", str(out)]) == 0
    table = capsys.readouterr().out
    assert first.split("rows:")[0].split("\n", 1)[1] in table


def test_malformed_grid_problem_and_result_files_exit_2(tmp_path, capsys):
    folder = _folder(tmp_path)
    bad_dir = tmp_path / "bad"
    bad_dir.mkdir()
    np.savez(bad_dir / "x.npz", source=np.zeros((5, 3)))
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "trials.csv").write_text("a,b\n1,2\n")
    broken = tmp_path / "broken"
    broken.mkdir()
    header = ",".join(TRIAL_COLUMNS)
    (broken / "trials.csv").write_text(header + "\nsynthetic,x,1,gnc,notanint\n")
    cases = {
        "--n 2": (["--n", "2"], "--n values must be >= 3"),
        "--trials 0": (["--trials", "0"], "--trials must be >= 1"),
        "--outlier-ratios 1": (["--outlier-ratios", "0.5", "1"], "in [0, 1)"),
        "--noise -1": (["--noise", "-1"], "--noise must be a positive"),
        "--batch-size 0": (["--batch-size", "0"], "--batch-size must be >= 1"),
        "--workers -1": (["--workers", "-1"], "--workers must be >= 0"),
        "twice": (["--solvers", "gnc", "gnc"], "lists a solver twice"),
        "no folder": (["--problems", str(tmp_path / "nowhere")], "does not exist"),
        "empty folder": (["--problems", str(foreign)], "holds no .npz"),
        "bad problem": (["--problems", str(bad_dir)], "missing key(s) target"),
        "same name": (["--problems", str(folder), str(tmp_path / "x" / "mine")], ""),
        "no data": (["--suite", "3dmatch", "--data", str(tmp_path)], "3dmatch suite needs"),
        "report missing": (["--report", str(tmp_path / "nowhere")], "does not exist"),
        "report foreign": (["--report", str(foreign)], "not a certpose bench row file"),
        "report broken": (["--report", str(broken)], "line 2 is not a valid row"),
        "report and suite": (["--report", str(broken), "--suite", "bunny"], "takes no --suite"),
    }
    shutil.copytree(folder, tmp_path / "x" / "mine")
    for label, (args, needle) in cases.items():
        rc = main(["bench", "--workers", "0", "--no-progress", *args])
        err = capsys.readouterr().err.strip()
        assert rc == 2, (label, rc, err)
        assert err.startswith("certpose bench: error:") and "\n" not in err, (label, err)
        assert needle in err, (label, err)
    with pytest.raises(SystemExit) as info:  # argparse: unknown suite
        main(["bench", "--suite", "kitti"])
    assert info.value.code == 2


def test_teaser_peer_is_skipped_cleanly_when_missing(tmp_path, capsys):
    from certpose.bench.runner import DEFAULT_SOLVERS, teaser_available

    if teaser_available():
        pytest.skip("teaserpp_python is installed here")
    assert "teaser++" not in DEFAULT_SOLVERS
    out = tmp_path / "res"
    assert main(["bench", "--n", "10", "--outlier-ratios", "0", "--trials", "1", "--solvers",
                 "gnc", "teaser++", "--workers", "0", "--no-progress", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "skipped teaser++: cannot import its backend" in captured.out
    assert "teaserpp_python" in captured.out
    data = strict_json((out / "bench.json").read_text())
    assert "teaser++" in data["skipped"] and {r["solver"] for r in data["summary"]} == {"gnc"}


@pytest.mark.slow  # FPFH features of the real scans (seconds) and a dense consistency graph
def test_threedmatch_suite_row(tmp_path):
    data = require_data("3dmatch", "gt.npy").parents[1]
    config = BenchConfig(suites=("3dmatch",), solvers=("gnc",), data_dir=str(data))
    report = run_benchmark(config, progress=False, out_dir=tmp_path / "res")
    (row,) = report.trials
    assert row["suite"] == "3dmatch" and row["instance"] == "pair" and row["n"] > 500
    assert 0.8 < row["outlier_ratio"] < 1.0  # real FPFH matches: mostly outliers
    assert row["success"], row  # < 5 deg and < 0.1 m
    assert row["rotation_error_deg"] < 5 and row["translation_error"] < 0.1
    assert row["cost"] > 0 and row["error"] == ""


@pytest.mark.slow  # builds a synthetic scene (seconds)
def test_eq2_suite_rows(tmp_path):
    config = BenchConfig(suites=("eq2",), solvers=("gnc", "gnc+cert-rotation"), trials=1,
                         data_dir=str(tmp_path))  # no ycbv here: the synthetic scene only
    report = run_benchmark(config, progress=False, out_dir=tmp_path / "res")
    rows = report.trials
    assert {r["instance"] for r in rows} == {"synthetic-s0"} and len(rows) == 2
    cert = next(r for r in rows if r["solver"] == "gnc+cert-rotation")
    assert cert["cert_problem"] == "rotation_tim_subproblem"
    assert cert["n"] >= 100 and np.isfinite(cert["translation_error"])
    assert report.scopes and report.scopes[0]["cert_problem"] == "rotation_tim_subproblem"
