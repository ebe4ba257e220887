"""``certpose register`` on real files (the bunny) and on malformed files."""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose.cli import main
from certpose.data.threedmatch import load_threedmatch_pair
from certpose.io.points import load_bunny
from solvers.lie import rotation_error_deg, transform_points
from tests.conftest import require_data, strict_json

ROOT = Path(__file__).resolve().parents[1]
SIGMA = 0.01
BETA = 5.54 * SIGMA


@pytest.fixture(scope="module")
def bunny_problem():
    """200 bunny correspondences, 30% outliers, with the ground-truth pose."""
    rng = np.random.default_rng(11)
    pts = load_bunny(require_data("bunny", "bun_zipper_res3.ply"))
    src = pts[rng.choice(pts.shape[0], size=200, replace=False)]
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-0.5, 0.5, size=3)
    dst = transform_points(T, src) + SIGMA * rng.normal(size=src.shape)
    out = rng.choice(200, size=60, replace=False)
    dst[out] = rng.uniform(-2.0, 2.0, size=(60, 3))
    weights = np.ones(200)
    weights[:10] = 0.5
    return src, dst, T, weights


def _write(path, pts: np.ndarray) -> None:
    suffix = path.suffix
    if suffix == ".npy":
        np.save(path, pts)
    elif suffix == ".csv":
        np.savetxt(path, pts, delimiter=",", header="x,y,z", comments="", fmt="%.17g")
    elif suffix == ".ply":
        import open3d as o3d

        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        assert o3d.io.write_point_cloud(str(path), cloud)
    else:
        raise AssertionError(suffix)


def _check_pose(json_path, T_gt: np.ndarray) -> dict:
    data = strict_json(json_path.read_text())
    res = data["result"]
    T = np.array(res["T_target_source"])
    assert res["success"] and res["status"] == "converged"
    assert rotation_error_deg(T[:3, :3], T_gt[:3, :3]) < 2.0
    assert np.linalg.norm(T[:3, 3] - T_gt[:3, 3]) < 0.02
    return data


@pytest.mark.parametrize("src_fmt,dst_fmt", [(".npy", ".csv"), (".ply", ".npy"), (".csv", ".ply")])
def test_register_bunny_files(tmp_path, bunny_problem, capsys, src_fmt, dst_fmt):
    src, dst, T_gt, _ = bunny_problem
    src_path, dst_path = tmp_path / f"src{src_fmt}", tmp_path / f"dst{dst_fmt}"
    _write(src_path, src)
    _write(dst_path, dst)
    out = tmp_path / "result.json"
    rc = main(["register", str(src_path), str(dst_path), "--noise-bound", str(BETA),
               "--json", str(out)])
    assert rc == 0
    data = _check_pose(out, T_gt)
    assert data["inputs"]["num_correspondences"] == 200
    assert data["inputs"]["noise_bound"] == BETA
    # The 140 inliers are found (a few noisy ones may fall just outside beta; no outlier in).
    inl = set(data["result"]["inliers"])
    assert 130 <= len(inl) <= 140
    stdout = capsys.readouterr().out
    assert "T_target_source" in stdout and "converged" in stdout


def test_register_weights_and_prune_never(tmp_path, bunny_problem):
    src, dst, T_gt, w = bunny_problem
    _write(tmp_path / "s.npy", src)
    _write(tmp_path / "d.npy", dst)
    np.savetxt(tmp_path / "w.csv", w)
    out = tmp_path / "r.json"
    rc = main(["register", str(tmp_path / "s.npy"), str(tmp_path / "d.npy"),
               "--noise-bound", str(BETA), "--weights", str(tmp_path / "w.csv"),
               "--prune", "never", "--json", str(out)])
    assert rc == 0
    data = _check_pose(out, T_gt)
    assert data["inputs"]["prune"] == "never"
    assert data["result"]["solver"] == "gnc"
    # The cost is the weighted TLS cost: recompute it from the returned pose.
    T = np.array(data["result"]["T_target_source"])
    r2 = np.sum((dst - transform_points(T, src)) ** 2, axis=1) / BETA**2
    assert data["result"]["cost"] == pytest.approx(float(w @ np.minimum(r2, 1.0)), rel=1e-9)


def test_register_fpfh_matches_two_scans_first(tmp_path, capsys):
    """``--fpfh VOXEL``: two real scans (the shared 3DMatch pair's files, different sizes) are
    matched, then registered: the pose is the ground truth's."""
    data = require_data("3dmatch", "gt.npy").parent
    out = tmp_path / "r.json"
    rc = main(["register", str(data / "src.npy"), str(data / "ref.npy"), "--fpfh", "0.05",
               "--noise-bound", "0.05", "--json", str(out)])
    assert rc == 0
    res = strict_json(out.read_text())
    assert res["inputs"]["fpfh_voxel"] == 0.05 and 500 <= res["inputs"]["num_correspondences"] <= 2000
    T = np.array(res["result"]["T_target_source"])
    G = load_threedmatch_pair(data).T_target_source
    assert rotation_error_deg(T[:3, :3], G[:3, :3]) < 5
    assert np.linalg.norm(T[:3, 3] - G[:3, 3]) < 0.1
    assert "FPFH correspondences (voxel 0.05)" in capsys.readouterr().out
    # Without --fpfh the same files are not row-matched correspondences: refused.
    assert main(["register", str(data / "src.npy"), str(data / "ref.npy"),
                 "--noise-bound", "0.05"]) == 2


@pytest.mark.slow  # over 3 s
def test_register_subprocess(tmp_path, bunny_problem):
    src, dst, T_gt, _ = bunny_problem
    _write(tmp_path / "s.ply", src)
    _write(tmp_path / "d.csv", dst)
    out = tmp_path / "r.json"
    proc = subprocess.run(
        [sys.executable, "-m", "certpose", "register", str(tmp_path / "s.ply"),
         str(tmp_path / "d.csv"), "--noise-bound", str(BETA), "--json", str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    _check_pose(out, T_gt)
    assert "inliers" in proc.stdout


def test_register_demo(tmp_path, capsys):
    out = tmp_path / "demo.json"
    assert main(["register", "--demo", "--json", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "rotation error" in stdout and "translation error" in stdout and "ms" in stdout
    data = strict_json(out.read_text())
    assert data["inputs"]["demo"] and data["inputs"]["outlier_ratio"] == 0.8
    T = np.array(data["result"]["T_target_source"])
    T_gt = np.array(data["ground_truth"]["T_target_source"])
    assert rotation_error_deg(T[:3, :3], T_gt[:3, :3]) == pytest.approx(
        data["errors"]["rotation_deg"])
    assert data["errors"]["rotation_deg"] < 5.0 and data["errors"]["translation"] < 0.05


def _bad_cases(tmp_path, good: np.ndarray):
    nan = good.copy()
    nan[3, 0] = np.nan
    np.save(tmp_path / "good.npy", good)
    np.save(tmp_path / "nan.npy", nan)
    np.save(tmp_path / "short.npy", good[:-5])
    np.save(tmp_path / "cols.npy", good[:, :2])
    (tmp_path / "garbage.csv").write_text("this is\nnot a point file\n")
    (tmp_path / "cols.csv").write_text("1,2\n3,4\n5,6\n")
    (tmp_path / "empty.csv").write_text("")
    (tmp_path / "broken.ply").write_text("ply\nnonsense\n")
    np.save(tmp_path / "w_short.npy", np.ones(3))
    g = str(tmp_path / "good.npy")
    return {
        "missing": ([g, str(tmp_path / "missing.npy")], "does not exist"),
        "garbage": ([g, str(tmp_path / "garbage.csv")], "garbage.csv"),
        "wrong columns csv": ([str(tmp_path / "cols.csv"), g], "cols.csv"),
        "wrong columns npy": ([g, str(tmp_path / "cols.npy")], "shape (N, 3)"),
        "empty": ([g, str(tmp_path / "empty.csv")], "empty"),
        "nan": ([str(tmp_path / "nan.npy"), g], "NaN"),
        "mismatched lengths": ([g, str(tmp_path / "short.npy")], "short.npy"),
        "broken ply": ([g, str(tmp_path / "broken.ply")], "broken.ply"),
        "short weights": ([g, g, "--weights", str(tmp_path / "w_short.npy")], "w_short.npy"),
        "bad noise bound": ([g, g, "--noise-bound", "-1"], "noise_bound"),
        "no files": ([], "SRC and DST"),
    }


def test_register_malformed_files(tmp_path, capsys):
    good = np.random.default_rng(0).normal(size=(20, 3))
    for label, (args, needle) in _bad_cases(tmp_path, good).items():
        argv = ["register", *args]
        if "--noise-bound" not in args:
            argv += ["--noise-bound", "0.05"]
        rc = main(argv)
        captured = capsys.readouterr()
        assert rc != 0, label
        err = captured.err.strip()
        assert err.startswith("certpose register: error:"), (label, err)
        assert "\n" not in err, (label, err)  # one line, no traceback
        assert needle in err, (label, err)


def test_register_malformed_subprocess(tmp_path):
    (tmp_path / "garbage.csv").write_text("1,2,banana\n")
    np.save(tmp_path / "good.npy", np.zeros((1, 3)))
    proc = subprocess.run(
        [sys.executable, "-m", "certpose", "register", str(tmp_path / "good.npy"),
         str(tmp_path / "garbage.csv"), "--noise-bound", "0.1"],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 2  # bad input
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "garbage.csv" in lines[0], proc.stderr


def test_register_demo_certificate_options(tmp_path, capsys):  # type: ignore[no-untyped-def]
    """--certify bounds the full problem by default; --scope/--tol reach the certificate."""
    from tests.conftest import strict_json

    out = tmp_path / "full.json"
    assert main(["register", "--demo", "--demo-outliers", "0.9", "--certify", "--json", str(out)]) == 0
    cert = strict_json(out.read_text())["result"]["certificate"]
    assert cert["problem"] == "full_weighted_tls" and cert["certified"] is True
    assert cert["cliques"] and cert["weight_scale"] == 1.0
    assert "it covers the returned pose" in capsys.readouterr().out
    out = tmp_path / "tim.json"
    assert main(["register", "--demo", "--certify", "--scope", "rotation", "--tol", "1e-2",
                 "--json", str(out)]) == 0
    cert = strict_json(out.read_text())["result"]["certificate"]
    assert cert["problem"] == "rotation_tim_subproblem" and cert["tol"] == 1e-2
    assert cert["pairs"] and cert["indices"]


def test_register_bad_certificate_options(capsys):  # type: ignore[no-untyped-def]
    assert main(["register", "--demo", "--certify", "--time-limit", "-1"]) == 2
    err = capsys.readouterr().err
    assert "time_limit" in err and "Traceback" not in err


@pytest.mark.parametrize("argv, names", [
    (["--demo", "--scope", "rotation"], "--scope concerns the certificate"),
    (["--demo", "--tol", "0.1", "--time-limit", "5"], "--tol/--time-limit concern the certificate"),
    (["--demo", "--solver", "sdp", "--prune", "never"], "--prune applies to --solver gnc"),
    (["--demo", "--weights", "w.npy"], "--weights does not apply to --demo"),
    (["a.npy", "b.npy", "--noise-bound", "0.1", "--demo-n", "20"], "--demo-n sets the --demo"),
    (["--demo", "--fpfh", "0.05"], "--fpfh matches the scans SRC DST"),
    (["a.npy", "b.npy", "--noise-bound", "0.1", "--fpfh", "0.05", "--weights", "w.npy"],
     "--weights does not apply to --fpfh"),
    (["a.npy", "b.npy", "--noise-bound", "0.1", "--fpfh", "0"], "--fpfh must be a positive"),
])
def test_register_refuses_options_it_would_ignore(capsys, argv, names):  # type: ignore[no-untyped-def]
    # Each of these ran without the option having any effect (a rotation scope without a
    # certificate, a demo size for files...).
    assert main(["register", *argv]) == 2
    err = capsys.readouterr().err
    assert names in err and err.count("\n") == 1, err


def test_negative_seed_is_refused_by_the_parser(capsys):  # type: ignore[no-untyped-def]
    # NumPy's own error did not name the option ("expected non-negative integer").
    for command in (["register", "--demo"], ["pose", "--demo"], ["bench", "--workers", "0"]):
        with pytest.raises(SystemExit) as info:
            main([*command, "--seed", "-5"])
        err = capsys.readouterr().err
        assert info.value.code == 2 and "argument --seed: must be a non-negative integer" in err


def test_register_certificate_options_with_a_certificate(capsys):  # type: ignore[no-untyped-def]
    # The same options are taken wherever a certificate is computed.
    assert main(["register", "--demo", "--require-certificate", "--tol", "0.01", "-q"]) == 0
    assert main(["register", "--demo", "--solver", "sdp", "--scope", "rotation", "--time-limit",
                 "60", "-q"]) == 0
    assert capsys.readouterr().err == ""


def _documented_command_lines() -> list[str]:
    """Every `certpose ...` line of the README's and the docs' shell blocks and of the commands' --help
    examples (continuation lines joined, comments cut; optional [...] parts kept, lines with
    alternatives a|b skipped)."""
    import re

    from certpose.cli import build_parser

    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    texts = [t for page in pages for t in re.findall(r"```bash\n(.*?)```", page.read_text(), re.S)]
    n_readme = len(texts)
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, command in sub.choices.items():
        texts.append(command.format_help())
        if name == "object":
            texts.append(command._subparsers._group_actions[0].choices["build"].format_help())
    lines = []
    for k, text in enumerate(texts):
        readme = k < n_readme
        for line in text.replace("\\\n", " ").splitlines():
            line = line.split("  #")[0].strip()
            if readme and "&& certpose " in line:  # e.g. "pip install ... && certpose pose --demo"
                line = line[line.rfind("&& certpose ") + 3:]
            if (line.startswith("certpose ") and "|" not in line and "..." not in line
                    and "`" not in line and "[-h]" not in line):
                lines.append(line.replace("[", "").replace("]", ""))
    return lines


def test_documented_command_lines_parse():
    # The README, the docs and the --help examples cannot name an option the parser lost or renamed.
    import shlex

    from certpose.cli import build_parser

    lines = _documented_command_lines()
    assert len(lines) >= 20 and any("object build" in x for x in lines)
    for line in lines:
        argv = shlex.split(line)[1:]
        try:
            build_parser(argv[0]).parse_args(argv)
        except SystemExit as exc:  # argparse's error (exit 2), printed above
            raise AssertionError(f"documented command does not parse: {line}") from exc


def test_console_script_and_python_m_run_the_same_program(tmp_path):
    import tomllib

    from certpose import cli

    scripts = tomllib.loads((Path(cli.__file__).parents[2] / "pyproject.toml").read_text())
    target = scripts["project"]["scripts"]["certpose"]
    module, _, name = target.partition(":")
    assert getattr(importlib.import_module(module), name) is cli.run
    # `run` exits with main's code: 2 for an unknown command, 0 for --version.
    for args, code in ((["no-such-command"], 2), (["--version"], 0)):
        proc = subprocess.run([sys.executable, "-m", "certpose", *args], capture_output=True,
                              text=True, timeout=120)
        assert proc.returncode == code, proc.stderr
    assert "certpose" in proc.stdout


def test_program_defers_open3d_plotly_until_it_is_used(tmp_path):
    # `certpose` skips open3d's Plotly/Dash import (about 1.3 s a run); its functions still work.
    code = textwrap.dedent("""
        import sys
        from certpose.cli import defer_open3d_plotly
        defer_open3d_plotly()
        import numpy as np
        import open3d as o3d
        loaded = "dash" in sys.modules
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.rand(5, 3)))
        fig = o3d.visualization.get_plotly_fig([cloud])
        print(loaded, type(fig).__name__, "dash" in sys.modules)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["False", "Figure", "True"]


def test_program_defers_numpy_tool_packages_until_they_are_used():
    # `certpose` skips numpy.f2py and numpy.testing, which SciPy's array_api_compat imports
    # (~0.09 s a run); they still work, also when threads reach them at once.
    code = textwrap.dedent("""
        import sys, threading
        from certpose.cli import defer_numpy_extras
        defer_numpy_extras()
        import numpy as np
        import scipy.linalg  # scipy._lib copies every public name of numpy
        heavy = ("numpy.f2py.crackfortran", "charset_normalizer", "numpy.testing._private")
        before = [n for n in heavy if n in sys.modules]
        barrier, errors = threading.Barrier(8), []
        def use():
            barrier.wait()
            try:
                np.testing.assert_array_equal(np.arange(3), [0, 1, 2])
            except Exception as exc:
                errors.append(repr(exc))
        threads = [threading.Thread(target=use) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        from numpy.f2py import crackfortran
        print(before, errors, callable(crackfortran.crackfortran), "numpy.testing._private" in sys.modules)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["[]", "[]", "True", "True"]


def test_pose_start_up_leaves_unused_modules_unloaded():
    # What `certpose pose --ycbv` imports before its scene: the frame (Pillow reads its PNGs,
    # scipy.io its meta.mat) and the progress bar's check (no terminal: no tqdm).
    root = require_data("ycbv")
    code = textwrap.dedent(f"""
        import argparse, sys
        from certpose.cli import busy, defer_numpy_extras
        defer_numpy_extras()
        from certpose.io.ycbv import load_ycbv_frame
        with busy(argparse.Namespace(quiet=False), "test", delay=0.0):
            frame = load_ycbv_frame({str(root)!r}, "0000/000001")
        lazy = ("imageio", "tqdm", "charset_normalizer", "numpy.f2py.crackfortran")
        print(frame.label.shape, [n for n in lazy if n in sys.modules])
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300, stdin=subprocess.DEVNULL)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "(480, 640) []"


def test_a_command_builds_only_its_own_parser():
    # `certpose pose ...` does not import the other commands (bench's alone costs ~0.2 s a run);
    # the program's own help and an unknown command still list them all.
    code = textwrap.dedent("""
        import sys
        from certpose.cli import build_parser
        sub = build_parser("pose")._subparsers._group_actions[0]
        alone = sorted(sub.choices), "certpose.cli.bench" in sys.modules
        everything = sorted(build_parser(None)._subparsers._group_actions[0].choices)
        unknown = sorted(build_parser("posee")._subparsers._group_actions[0].choices)
        print(alone, everything == unknown, everything)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == ("(['pose'], False) True "
                                 "['bench', 'bop', 'object', 'pose', 'register', 'score']")
    helped = subprocess.run([sys.executable, "-m", "certpose", "pose", "--help"],
                            capture_output=True, text=True, timeout=300)
    assert helped.returncode == 0 and "--ycbv" in helped.stdout
