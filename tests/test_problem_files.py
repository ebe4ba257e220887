"""Problem files (.npz): strict reading and writing, `certpose register --problem` (a real
subprocess), `certpose pose --save-problem`, and the CLI's exit codes and one-line errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from certpose.cli import main
from certpose.data.instances import make_instance
from certpose.io.points import synthetic_shape
from certpose.io.problems import load_problem, save_problem

ROOT = Path(__file__).resolve().parents[1]


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "certpose", *args], capture_output=True,
                          text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})


def _problem(tmp_path: Path, name: str = "p.npz", *, seed: int = 1, ratio: float = 0.8,
             gt: bool = True, **meta) -> tuple[Path, np.ndarray]:
    inst = make_instance(synthetic_shape(), 60, ratio, noise=0.01, rng=seed)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = inst.rotation, inst.translation
    path = save_problem(tmp_path / name, inst.source, inst.target, noise_bound=inst.noise_bound,
                        weights=np.linspace(0.5, 1.5, 60), T_target_source=T if gt else None,
                        metadata={"suite": "mine", "name": name, **meta})
    return path, T


def test_problem_file_round_trip(tmp_path):
    path, T = _problem(tmp_path, rotation_tol_deg=3.0)
    p = load_problem(path)
    assert p.n == 60 and p.source.shape == p.target.shape == (60, 3)
    np.testing.assert_allclose(p.weights, np.linspace(0.5, 1.5, 60))
    assert p.noise_bound == pytest.approx(0.0554)
    np.testing.assert_array_equal(p.T_target_source, T)
    assert p.metadata == {"suite": "mine", "name": "p.npz", "rotation_tol_deg": 3.0}
    assert p.outlier_ratio() == pytest.approx(0.8)
    # Per-correspondence bounds are kept as an array.
    q = save_problem(tmp_path / "q.npz", p.source, p.target, noise_bound=np.full(60, 0.1))
    assert load_problem(q).noise_bound.shape == (60,) and load_problem(q).T_target_source is None


def _bad_files(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    good = {"source": np.zeros((5, 3)), "target": np.ones((5, 3)), "weights": np.ones(5),
            "noise_bounds": np.float64(0.1)}
    cases = {
        "missing target": ({k: v for k, v in good.items() if k != "target"}, "missing key(s) target"),
        "wrong shape": ({**good, "target": np.zeros((5, 2))}, "shape (5, 3), got (5, 2)"),
        "NaN": ({**good, "source": np.full((5, 3), np.nan)}, "`source` contains NaN"),
        "negative weight": ({**good, "weights": -np.ones(5)}, "non-negative"),
        "zero bound": ({**good, "noise_bounds": np.float64(0.0)}, "`noise_bounds` must be positive"),
        "bounds shape": ({**good, "noise_bounds": np.ones(4)}, "shape (5,), got (4,)"),
        "extra key": ({**good, "colour": np.ones(5)}, "unexpected key(s) colour"),
        "not rigid": ({**good, "T_target_source": 2 * np.eye(4)}, "not a rigid transform"),
        "bad metadata": ({**good, "metadata": np.asarray("{oops")}, "not valid JSON"),
    }
    out = {}
    for label, (arrays, needle) in cases.items():
        path = tmp_path / f"{label.replace(' ', '_')}.npz"
        np.savez(path, **arrays)
        out[label] = (path, needle)
    text = tmp_path / "text.npz"
    text.write_text("source,target\n")
    out["not an archive"] = (text, "not a .npz archive")
    out["missing file"] = (tmp_path / "nowhere.npz", "does not exist")
    return out


def test_malformed_problem_files_raise_one_line_errors(tmp_path):
    for label, (path, needle) in _bad_files(tmp_path).items():
        with pytest.raises((ValueError, OSError)) as info:
            load_problem(path)
        msg = str(info.value)
        assert needle in msg and "\n" not in msg and str(path) in msg, (label, msg)
    with pytest.raises(ValueError, match="must end in .npz"):
        save_problem(tmp_path / "p.txt", np.zeros((5, 3)), np.zeros((5, 3)), noise_bound=1.0)
    with pytest.raises(ValueError, match="NaN"):  # never writes a file it would refuse
        save_problem(tmp_path / "n.npz", np.full((5, 3), np.nan), np.zeros((5, 3)),
                     noise_bound=1.0)
    assert not (tmp_path / "n.npz").exists()


@pytest.mark.slow  # two subprocesses (about 4 s)
def test_register_problem_subprocess_round_trip(tmp_path):
    path, T = _problem(tmp_path)
    out = tmp_path / "res.json"
    proc = _cli("register", "--problem", str(path), "--json", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "rotation error" in proc.stdout and "suite mine" in proc.stdout
    data = json.loads(out.read_text())
    assert data["inputs"]["num_correspondences"] == 60
    assert data["inputs"]["metadata"]["suite"] == "mine"
    assert data["ground_truth"]["T_target_source"] == T.tolist()
    assert data["errors"]["rotation_deg"] < 3 and data["errors"]["translation"] < 0.03
    # The file's weights reach the solver: its cost is the weighted one.
    assert data["result"]["success"] is True
    # --json - prints only JSON on stdout.
    proc = _cli("register", "--problem", str(path), "--json", "-")
    assert proc.returncode == 0 and json.loads(proc.stdout)["errors"]["rotation_deg"] < 3


def test_register_exit_codes(tmp_path, capsys):
    path, _ = _problem(tmp_path)
    # Bad input: exit 2 with one line, for every malformed file.
    for label, (bad, needle) in _bad_files(tmp_path).items():
        assert main(["register", "--problem", str(bad)]) == 2, label
        err = capsys.readouterr().err.strip()
        assert err.startswith("certpose register: error:") and "\n" not in err, (label, err)
        assert needle in err, (label, err)
    assert main(["register", "--problem", str(path), "--weights", "w.npy"]) == 2
    assert "--weights" in capsys.readouterr().err
    # A certificate asked for and not obtained: exit 1 (a gap above 1e-300 is not certified).
    assert main(["register", "--problem", str(path), "--require-certificate", "--quiet",
                 "--tol", "1e-300"]) == 1
    captured = capsys.readouterr()
    assert captured.out == "" and "not certified" in captured.err
    assert main(["register", "--problem", str(path), "--require-certificate", "-q"]) == 0
    # --verbose shows the traceback of a bad input; without it, one line.
    assert main(["register", "--problem", str(tmp_path / "nowhere.npz"), "-v"]) == 2
    assert "Traceback" in capsys.readouterr().err


def test_python_m_certpose_help():
    proc = _cli("--help")
    assert proc.returncode == 0
    for cmd in ("register", "bench", "pose", "object"):
        assert cmd in proc.stdout
    assert "exit codes" in proc.stdout
    with pytest.raises(SystemExit) as info:
        main(["register", "--problem"])
    assert info.value.code == 2


@pytest.mark.slow  # the full pose pipeline on the synthetic scene
def test_pose_save_problem_round_trips_through_register(tmp_path):
    out, js = tmp_path / "eq2.npz", tmp_path / "pose.json"
    rc = main(["pose", "--demo", "--save-problem", str(out), "--require-certificate", "-q",
               "--json", str(js)])
    cert = json.loads(js.read_text())["certificate"]
    # Exit 0 exactly when the eq. (2) solution is certified (--require-certificate).
    assert rc == (0 if cert is not None and cert["certified"] else 1)
    p = load_problem(out)
    assert p.metadata["suite"] == "eq2" and p.metadata["symmetry_axis"] == [0.0, 0.0, 1.0]
    assert p.T_target_source is not None and p.n >= 100
    assert np.all(p.weights >= 0) and p.noise_bound == pytest.approx(0.005)
    proc = _cli("register", "--problem", str(out), "--json", "-")
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    # eq. (2) approximates the pose (5 mm grid): its minimiser is near the object's true pose.
    assert data["errors"]["translation"] < 0.05
