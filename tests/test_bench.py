"""``certpose bench``: instances follow the protocol; a tiny grid with every peer."""

from __future__ import annotations

import csv
import sys

import numpy as np
import pytest

from certpose.bench.runner import (
    SOLVERS,
    SUMMARY_COLUMNS,
    TRIAL_COLUMNS,
    BenchConfig,
    run_benchmark,
)
from certpose.cli import main
from certpose.data.instances import make_instance
from certpose.io.points import synthetic_shape
from tests.conftest import strict_json

PEERS = ["gnc", "gnc-only", "gtsam-gnc", "o3d-ransac", "o3d-fgr"]


def test_make_instance_follows_protocol():
    shape = synthetic_shape()
    inst = make_instance(shape, 200, 0.7, noise=0.01, rng=5)
    assert inst.source.shape == inst.target.shape == (200, 3)
    assert inst.outliers.sum() == 140
    assert inst.noise_bound == pytest.approx(0.0554)
    # Source points are shape points; the ground truth is a rotation and |t| <= 1.
    assert np.all(np.isin(inst.source, shape))
    np.testing.assert_allclose(inst.rotation.T @ inst.rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(inst.rotation) == pytest.approx(1.0)
    assert np.linalg.norm(inst.translation) <= 1.0
    # Inlier residuals are N(0, sigma^2 I); outliers lie in the ball of radius 5.
    res = inst.target - inst.source @ inst.rotation.T - inst.translation
    inl = res[~inst.outliers]
    assert 0.007 < inl.std() < 0.013
    assert np.all(np.linalg.norm(inst.target[inst.outliers], axis=1) <= 5.0)
    assert np.linalg.norm(inst.target[inst.outliers], axis=1).max() > 3.0
    # Same seed, same instance; another seed, another instance.
    again = make_instance(shape, 200, 0.7, noise=0.01, rng=5)
    np.testing.assert_array_equal(again.target, inst.target)
    other = make_instance(shape, 200, 0.7, noise=0.01, rng=6)
    assert not np.array_equal(other.target, inst.target)


def test_make_instance_rejects_bad_input():
    shape = synthetic_shape()
    with pytest.raises(ValueError, match="outlier_ratio"):
        make_instance(shape, 50, 1.0, noise=0.01)
    with pytest.raises(ValueError, match="`n`"):
        make_instance(shape, 2, 0.0, noise=0.01)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        make_instance(shape[:, :2], 20, 0.0, noise=0.01)


def test_config_validation():
    with pytest.raises(ValueError, match="unknown solver"):
        BenchConfig(solvers=("gnc", "teaser"))
    with pytest.raises(ValueError, match="outlier_ratios"):
        BenchConfig(outlier_ratios=(0.5, 1.2))
    with pytest.raises(ValueError, match="noise"):
        BenchConfig(noise=0.0)
    with pytest.raises(ValueError, match="trials"):
        BenchConfig(trials=0)
    assert BenchConfig().solvers == ("gnc", "gnc-only", "gtsam-gnc", "o3d-ransac", "o3d-fgr")


def _read_csv(path):
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        return reader.fieldnames, list(reader)


@pytest.mark.slow  # over 3 s
def test_bench_cli_tiny_grid_all_peers(tmp_path, capsys):
    out = tmp_path / "bench"
    rc = main(["bench", "--n", "20", "30", "--outlier-ratios", "0", "0.5", "--trials", "2",
               "--seed", "3", "--solvers", *PEERS, "--out", str(out), "--plot",
               "--no-progress", "--workers", "0"])
    assert rc == 0
    stdout = capsys.readouterr().out
    for name in PEERS:
        assert name in stdout

    fields, summary = _read_csv(out / "summary.csv")
    assert tuple(fields) == SUMMARY_COLUMNS
    assert len(summary) == len(PEERS) * 2 * 2
    fields, trials = _read_csv(out / "trials.csv")
    assert tuple(fields) == TRIAL_COLUMNS
    assert len(trials) == len(PEERS) * 2 * 2 * 2
    assert all(float(t["time_ms"]) > 0 for t in trials)
    assert not any(t["error"] for t in trials), [t["error"] for t in trials if t["error"]]

    cell = {(r["solver"], int(r["n"]), float(r["outlier_ratio"])): r for r in summary}
    for n in (20, 30):
        # Without outliers every least-squares-based method must recover the pose.
        for name in ("gnc", "gnc-only", "gtsam-gnc"):
            row = cell[(name, n, 0.0)]
            assert float(row["success_rate"]) == 1.0, row
            assert float(row["median_rotation_error_deg"]) < 2.0
            assert float(row["median_translation_error"]) < 0.02
        assert float(cell[("gnc", n, 0.5)]["success_rate"]) == 1.0
        assert float(cell[("gtsam-gnc", n, 0.0)]["time_vs_gtsam"]) == pytest.approx(1.0)
        # certpose's self-reported solve time is part of the wall-clock time around the call.
        gnc = cell[("gnc", n, 0.0)]
        assert 0 < float(gnc["median_reported_time_ms"]) <= float(gnc["median_time_ms"])
        assert cell[("gtsam-gnc", n, 0.0)]["median_reported_time_ms"] == "nan"
        for name in PEERS:
            assert float(cell[(name, n, 0.0)]["median_time_ms"]) > 0
            assert cell[(name, n, 0.0)]["certified_fraction"] == "nan"

    data = strict_json((out / "bench.json").read_text())
    assert data["config"]["n_values"] == [20, 30]
    assert data["config"]["solvers"] == PEERS
    assert data["noise_bound"] == pytest.approx(0.0554)
    assert len(data["summary"]) == len(summary) and "trials" not in data  # rows: trials.csv
    assert data["skipped"] == {}

    import imageio.v3 as iio

    img = iio.imread(out / "bench.png")
    assert img.ndim == 3 and img.shape[0] > 100
    assert not (out / "certificates.png").exists()  # no certificates requested


def test_bench_bunny_option(tmp_path, capsys):
    from tests.conftest import require_data

    bunny = require_data("bunny", "bun_zipper_res3.ply")
    rc = main(["bench", "--bunny", str(bunny), "--n", "30", "--outlier-ratios", "0.2",
               "--trials", "1", "--solvers", "gnc", "--out", str(tmp_path), "--no-progress",
               "--workers", "0"])
    assert rc == 0
    data = strict_json((tmp_path / "bench.json").read_text())
    assert data["shape"] == str(bunny)
    assert data["summary"][0]["success_rate"] == 1.0


def test_bench_certified_solver(tmp_path):
    """``gnc+certify`` records certificates."""
    config = BenchConfig(n_values=(12,), outlier_ratios=(0.25,), trials=1, seed=1,
                         solvers=("gnc", "gnc+certify"))
    report = run_benchmark(config, progress=False)
    assert not report.skipped
    row = next(r for r in report.summary if r["solver"] == "gnc+certify")
    trial = next(t for t in report.trials if t["solver"] == "gnc+certify")
    # 12 correspondences, 3 outliers: GNC finds the optimum and the clique bound proves it.
    assert trial["certified"] is True, trial
    assert 0.0 <= trial["relative_gap"] <= 1e-3
    assert row["certified_fraction"] == 1.0
    assert trial["cert_problem"] == "full_weighted_tls"
    assert trial["lower_bound"] <= trial["upper_bound"]
    written = report.write(tmp_path, plot=True)
    assert tmp_path / "certificates.png" in written and tmp_path / "report.md" in written


def test_bench_cli_errors(capsys):
    assert main(["bench", "--plot", "--no-progress"]) == 2
    assert "--plot needs --out" in capsys.readouterr().err
    assert main(["bench", "--outlier-ratios", "1.5", "--no-progress"]) == 2
    assert "outlier_ratios" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse rejects unknown solver names
        main(["bench", "--solvers", "teaser"])
    assert set(SOLVERS) >= set(PEERS)


def test_bench_draws_no_progress_bar_into_a_log(capsys):
    # stderr captured, as when redirected to a file: the bar's carriage-return updates
    # ("certpose bench:  17%|...") used to be written there.
    assert main(["bench", "--n", "10", "--outlier-ratios", "0", "--trials", "2", "--solvers",
                 "gnc", "--workers", "0"]) == 0
    captured = capsys.readouterr()
    assert "gnc" in captured.out
    assert "certpose bench:" not in captured.err and "\r" not in captured.err, captured.err


def test_bench_names_the_extra_when_it_is_missing(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "tqdm", None)  # as if the bench extra were not installed
    assert main(["bench", "--n", "10", "--trials", "1", "--solvers", "gnc", "--workers", "0"]) == 1
    err = capsys.readouterr().err
    assert "needs tqdm" in err and "pip install 'certpose[bench]'" in err
