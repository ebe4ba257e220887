"""Issue #8, item 3: strict input and output.

Bad files, bad arguments and extreme scales give a one-line error (or a reported status), never
a traceback; JSON output is strict JSON; output paths are checked before the work; results are
immutable.
"""

from __future__ import annotations

import json
import math
import os
import pickle
from dataclasses import FrozenInstanceError

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from certpose.api import register
from certpose.cli import main
from certpose.io.output import check_output_path, to_json, write_json
from certpose.io.points import read_points
from certpose.io.ycbv import load_model_points
from solvers import WeightedTLSProblem
from solvers.lie import rotation_error_deg
from solvers.registration.solve import GNCParams, PruningParams, check_graph_memory
from solvers.result import RegistrationResult, SolverStatus
from solvers.validation import check_count, check_limit


def _instance(seed: int = 0, n: int = 60, n_out: int = 20):
    rng = np.random.default_rng(seed)
    src = rng.uniform(-0.5, 0.5, (n, 3))
    R, t = Rotation.random(random_state=rng).as_matrix(), rng.uniform(-1.0, 1.0, 3)
    dst = src @ R.T + t + 0.001 * rng.normal(size=src.shape)
    dst[:n_out] = rng.uniform(-2.0, 2.0, (n_out, 3))
    return src, dst, R, t


def _write_ply(path, pts: np.ndarray, *, binary: bool) -> None:
    from plyfile import PlyData, PlyElement

    vertex = np.array([tuple(p) for p in pts], dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    PlyData([PlyElement.describe(vertex, "vertex")], text=not binary).write(str(path))


def _run_cli(argv, capsys) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _assert_one_line_error(code: int, err: str, *patterns: str) -> None:
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for p in patterns:
        assert p in lines[0], lines[0]


# -- point files ----------------------------------------------------------------------------


@pytest.mark.parametrize("binary", [True, False])
def test_truncated_ply_is_rejected(tmp_path, binary):
    pts = np.random.default_rng(0).uniform(-1, 1, (50, 3))
    full = tmp_path / "full.ply"
    _write_ply(full, pts, binary=binary)
    np.testing.assert_array_equal(read_points(full), pts)
    data = full.read_bytes()
    cut = tmp_path / "cut.ply"
    cut.write_bytes(data[: len(data) - (len(data) - data.index(b"end_header")) // 2])
    with pytest.raises(ValueError, match="not a valid PLY file") as info:
        read_points(cut, name="source")
    assert "cut.ply" in str(info.value) and "\n" not in str(info.value)


def test_truncated_ply_cli_exits_nonzero(tmp_path, capsys):
    src, dst, _, _ = _instance()
    _write_ply(tmp_path / "src.ply", src, binary=True)
    data = (tmp_path / "src.ply").read_bytes()
    (tmp_path / "src.ply").write_bytes(data[:-200])
    np.save(tmp_path / "dst.npy", dst)
    code, _, err = _run_cli(["register", tmp_path / "src.ply", tmp_path / "dst.npy",
                             "--noise-bound", "0.01"], capsys)
    _assert_one_line_error(code, err, "src.ply", "not a valid PLY file")


def test_ply_without_xyz_is_rejected(tmp_path):
    from plyfile import PlyData, PlyElement

    el = PlyElement.describe(np.array([(1.0,), (2.0,)], dtype=[("u", "f8")]), "vertex")
    PlyData([el], text=True).write(str(tmp_path / "uv.ply"))
    with pytest.raises(ValueError, match="no x, y, z"):
        read_points(tmp_path / "uv.ply")


def test_one_xyz_parser(tmp_path):
    """The YCB-Video model reader is read_points: same checks, same messages."""
    good = tmp_path / "points.xyz"
    pts = np.random.default_rng(1).normal(size=(10, 3))
    np.savetxt(good, pts)
    np.testing.assert_allclose(load_model_points(good), read_points(good))
    bad = tmp_path / "nan.xyz"
    bad.write_text("1 2 3\n4 nan 6\n")
    with pytest.raises(ValueError, match="NaN or inf values in 1 row"):
        load_model_points(bad)
    empty = tmp_path / "empty.xyz"
    empty.write_text("\n")
    with pytest.raises(ValueError, match="empty"):
        load_model_points(empty)


@pytest.mark.parametrize(
    ("name", "content", "pattern"),
    [
        ("empty.csv", "", "empty"),
        ("nan.xyz", "1 2 3\nnan 1 2\n0 0 1\n", "NaN or inf"),
        ("garbage.npy", "not npy", "not a valid .npy"),
        ("garbage.ply", "ply\nformat nonsense\n", "not a valid PLY"),
    ],
)
def test_bad_point_files_cli(tmp_path, capsys, name, content, pattern):
    (tmp_path / name).write_text(content)
    np.save(tmp_path / "dst.npy", np.zeros((3, 3)))
    code, _, err = _run_cli(["register", tmp_path / name, tmp_path / "dst.npy",
                             "--noise-bound", "0.01"], capsys)
    _assert_one_line_error(code, err, name, pattern)


def test_unreadable_file_cli(tmp_path, capsys):
    if os.geteuid() == 0:
        pytest.skip("root reads any file")
    p = tmp_path / "src.npy"
    np.save(p, np.zeros((3, 3)))
    p.chmod(0)
    code, _, err = _run_cli(["register", p, p, "--noise-bound", "0.01"], capsys)
    _assert_one_line_error(code, err, "src.npy")


# -- JSON output ------------------------------------------------------------------------------


def test_to_json_maps_nonfinite_to_null():
    payload = {"a": float("nan"), "b": [np.inf, -np.inf, 1.5], "c": np.float32(np.nan),
               "d": np.array([1.0, np.nan]), "e": SolverStatus.CONVERGED, "f": (np.int64(3),)}
    text = to_json(payload)
    assert "NaN" not in text and "Infinity" not in text
    data = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-strict JSON {c}"))
    assert data == {"a": None, "b": [None, None, 1.5], "c": None, "d": [1.0, None],
                    "e": "converged", "f": [3]}


def test_register_json_is_strict_with_nan_in_certificate(tmp_path):
    """A certificate without a moment matrix (eigenvalue ratio NaN, lower bound -inf) still
    writes valid JSON: null."""
    from dataclasses import replace

    from solvers.certificate import Certificate

    src, dst, _, _ = _instance()
    cert = Certificate(upper_bound=1.0, lower_bound=-math.inf, relative_gap=math.inf,
                       certified=False, tol=1e-6, problem="full_weighted_tls",
                       eigenvalue_ratio=math.nan, backend_status="none", solve_time=0.0,
                       message="no dual point")
    res = replace(register(src, dst, noise_bound=0.01), certificate=cert)
    text = write_json(tmp_path / "r.json", {"result": res.to_dict()}).read_text()
    assert "NaN" not in text and "Infinity" not in text
    data = _strict_load(tmp_path / "r.json")
    c = data["result"]["certificate"]
    assert c["eigenvalue_ratio"] is None and c["lower_bound"] is None
    assert c["upper_bound"] == 1.0


def _strict_load(path):
    return json.loads(path.read_text(),
                      parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))


def test_register_demo_json_certified_is_strict(tmp_path, capsys):
    out = tmp_path / "demo.json"
    code, stdout, _ = _run_cli(["register", "--demo", "--demo-n", "40", "--certify",
                                "--json", out], capsys)
    assert code == 0, stdout
    data = _strict_load(out)
    assert data["result"]["certificate"] is not None


# -- output paths, checked before the work ---------------------------------------------------


@pytest.mark.parametrize("case", ["missing_dir", "is_dir"])
def test_output_path_checked_before_work(tmp_path, capsys, monkeypatch, case):
    target = tmp_path / "nope" / "out.json" if case == "missing_dir" else tmp_path
    # The solve must not start: make it fail loudly if it does.
    import certpose.api

    def boom(*a, **k):
        raise AssertionError("the solve started before the output path was checked")

    monkeypatch.setattr(certpose.api, "register", boom)
    code, _, err = _run_cli(["register", "--demo", "--json", target], capsys)
    _assert_one_line_error(code, err, str(target))
    code, _, err = _run_cli(["pose", "--demo", "--json", target], capsys)
    _assert_one_line_error(code, err, str(target))


def test_output_path_not_writable(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root writes anywhere")
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o500)
    with pytest.raises(OSError, match="not writable"):
        check_output_path(d / "x.json")


def test_bench_out_checked_before_work(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    code, _, err = _run_cli(["bench", "--trials", "1", "--out", f], capsys)
    _assert_one_line_error(code, err, str(f), "not a directory")
    code, _, err = _run_cli(["bench", "--trials", "1", "--out", f / "sub"], capsys)
    _assert_one_line_error(code, err, str(f / "sub"), "not a directory")


# -- exit codes -------------------------------------------------------------------------------


def test_register_failed_solve_exits_nonzero(tmp_path, capsys):
    """Collinear correspondences cannot fix a rotation: the solve fails, the exit code says so."""
    s = np.linspace(0, 1, 20)
    line = np.column_stack([s, 2 * s, -s])
    np.save(tmp_path / "src.npy", line)
    np.save(tmp_path / "dst.npy", line + 1.0)
    out = tmp_path / "r.json"
    code, stdout, _ = _run_cli(["register", tmp_path / "src.npy", tmp_path / "dst.npy",
                                "--noise-bound", "0.01", "--json", out], capsys)
    assert code == 1
    assert "FAILED" in stdout
    data = _strict_load(out)
    assert data["result"]["success"] is False and data["result"]["status"] == "degenerate"


def test_register_success_exits_zero(tmp_path, capsys):
    src, dst, _, _ = _instance()
    np.save(tmp_path / "src.npy", src)
    np.save(tmp_path / "dst.npy", dst)
    code, stdout, _ = _run_cli(["register", tmp_path / "src.npy", tmp_path / "dst.npy",
                                "--noise-bound", "0.00554"], capsys)
    assert code == 0, stdout


# -- extreme scales ---------------------------------------------------------------------------


SCALES = [1e-200, 1e-150, 1e-100, 1e-20, 1.0, 1e20, 1e100, 1e150, 1e200]


@pytest.mark.parametrize("prune", ["auto", "never", "always"])
@pytest.mark.parametrize("scale", SCALES)
def test_extreme_scales_solve_alike(scale, prune):
    src, dst, R, t = _instance()
    ref = register(src, dst, noise_bound=0.00554, prune=prune)
    res = register(src * scale, dst * scale, noise_bound=0.00554 * scale, prune=prune)
    assert res.status is SolverStatus.CONVERGED, res.message
    assert rotation_error_deg(res.rotation, R) < 0.5
    np.testing.assert_allclose(res.translation / scale, ref.translation, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(res.inliers, ref.inliers)
    assert res.num_inliers == 40


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(exponent=st.integers(-200, 200), seed=st.integers(0, 2**16))
def test_extreme_scales_property(exponent, seed):
    scale = 10.0**exponent
    src, dst, R, t = _instance(seed, n=30, n_out=5)
    res = register(src * scale, dst * scale, noise_bound=0.00554 * scale)
    assert res.status is SolverStatus.CONVERGED, res.message
    assert rotation_error_deg(res.rotation, R) < 1.0
    assert np.linalg.norm(res.translation / scale - t) < 0.01


@pytest.mark.parametrize("prune", ["auto", "never", "always"])
def test_tiny_noise_bound_reports_status(prune):
    src, dst, _, _ = _instance()
    res = register(src, dst, noise_bound=1e-300, prune=prune)
    # No residual but an exact zero can meet 1e-300: too few inliers, reported not raised.
    assert res.status is SolverStatus.INSUFFICIENT_INLIERS, res.message
    assert np.all(np.isfinite(res.T_target_source))


def test_tiny_noise_bound_exact_data_converges():
    src, _, R, t = _instance()
    dst = src @ R.T + t
    res = register(src * 1e-150, dst * 1e-150, noise_bound=1e-300)
    assert res.status in set(SolverStatus)
    assert np.all(np.isfinite(res.T_target_source))


# -- pruning memory ---------------------------------------------------------------------------


def test_prune_always_refuses_huge_graph_before_allocating():
    n = 200_000
    from solvers.registration.solve import _available_memory

    avail = _available_memory()
    if avail is None or avail > 2 * n * n:
        pytest.skip("this machine could hold the 40 GB graph")
    rng = np.random.default_rng(0)
    src = rng.normal(size=(n, 3))
    with pytest.raises(MemoryError, match=r"N = 200000 .*40 GB"):
        register(src, src + 1.0, noise_bound=0.01, prune="always")
    with pytest.raises(MemoryError, match="200000"):
        check_graph_memory(n)
    check_graph_memory(1000)  # 1 MB is fine


def test_prune_always_refusal_cli(tmp_path, capsys):
    from solvers.registration.solve import _available_memory

    n = 200_000
    avail = _available_memory()
    if avail is None or avail > 2 * n * n:
        pytest.skip("this machine could hold the 40 GB graph")
    src = np.random.default_rng(0).normal(size=(n, 3))
    np.save(tmp_path / "src.npy", src)
    np.save(tmp_path / "dst.npy", src + 1.0)
    code, _, err = _run_cli(["register", tmp_path / "src.npy", tmp_path / "dst.npy",
                             "--noise-bound", "0.01", "--prune", "always"], capsys)
    _assert_one_line_error(code, err, "N = 200000", "GB")


# -- Open3D tensor clouds ---------------------------------------------------------------------


def test_open3d_tensor_point_clouds_accepted():
    o3d = pytest.importorskip("open3d")
    src, dst, R, t = _instance()
    legacy = register(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src)),
                      o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dst)),
                      noise_bound=0.00554)
    tensor = register(o3d.t.geometry.PointCloud(o3d.core.Tensor(src)),
                      o3d.t.geometry.PointCloud(o3d.core.Tensor(dst)), noise_bound=0.00554)
    np.testing.assert_array_equal(tensor.T_target_source, legacy.T_target_source)
    assert rotation_error_deg(tensor.rotation, R) < 0.5
    with pytest.raises(ValueError, match="`source` is an Open3D tensor point cloud without"):
        register(o3d.t.geometry.PointCloud(), dst, noise_bound=0.01)


# -- integer counts and limits ----------------------------------------------------------------


@pytest.mark.parametrize("bad", [10.5, True, "10", None])
def test_non_integer_iteration_counts_rejected(bad):
    with pytest.raises(TypeError, match="`max_iterations` must be an integer"):
        GNCParams(max_iterations=bad)
    with pytest.raises(TypeError, match="`max_tied_cliques` must be an integer"):
        PruningParams(max_tied_cliques=bad)


def test_negative_counts_and_limits_rejected():
    with pytest.raises(ValueError, match="`max_iterations` must be >= 1, got 0"):
        GNCParams(max_iterations=0)
    with pytest.raises(ValueError, match="`exact_clique_max_vertices` must be >= 0, got -1"):
        PruningParams(exact_clique_max_vertices=-1)
    with pytest.raises(ValueError, match="`time_limit` must be a non-negative finite number"):
        check_limit(-1.0, "time_limit")
    with pytest.raises(ValueError, match="`time_limit`"):
        check_limit(math.inf, "time_limit")
    with pytest.raises(TypeError, match="`time_limit` must be a number"):
        check_limit(True, "time_limit")
    assert check_limit(None, "time_limit") is None
    assert check_count(np.int64(5), "n") == 5 and GNCParams(max_iterations=np.int32(7))


# -- immutable results ------------------------------------------------------------------------


def test_results_are_immutable():
    src, dst, _, _ = _instance()
    res = register(src, dst, noise_bound=0.00554)
    R = res.rotation.copy()
    with pytest.raises(ValueError, match="read-only"):
        res.T_target_source[0, 0] = 5.0
    with pytest.raises(ValueError, match="read-only"):
        res.rotation[:] = 0.0
    with pytest.raises(ValueError, match="read-only"):
        res.inliers[0] = not res.inliers[0]
    with pytest.raises(FrozenInstanceError):
        res.status = SolverStatus.SOLVER_ERROR  # type: ignore[misc]
    with pytest.raises(TypeError):
        res.info["x"] = 1  # type: ignore[index]
    np.testing.assert_array_equal(res.rotation, R)
    # Still picklable (results travel to Dask workers) and equal after the round trip.
    back = pickle.loads(pickle.dumps(res))
    np.testing.assert_array_equal(back.T_target_source, res.T_target_source)
    assert dict(back.info) == dict(res.info)


def test_result_does_not_alias_caller_arrays():
    T = np.eye(4)
    res = RegistrationResult(T, np.ones(3, bool), 0.0, 1, 0.0, SolverStatus.CONVERGED, "ok")
    T[0, 3] = 9.0
    assert res.translation[0] == 0.0
    assert T.flags.writeable


def test_problem_arrays_read_only_do_not_break_solve():
    src, dst, R, _ = _instance()
    problem = WeightedTLSProblem(src, dst, noise_bound=0.00554)
    assert not problem.source.flags.writeable
    from solvers import solve_registration

    res = solve_registration(problem, method="gnc")
    assert rotation_error_deg(res.rotation, R) < 1.0


@pytest.mark.parametrize("scale", [1e-200, 1e200])
@pytest.mark.parametrize("kwargs", [{"certify": True}, {"solver": "sdp"}])
def test_extreme_scales_certify_alike(scale, kwargs):
    """Certificates are computed at unit scale: the same verdict and gap at any scale."""
    src, dst, _, _ = _instance(n=30, n_out=5)
    ref = register(src, dst, noise_bound=0.01, **kwargs)
    res = register(src * scale, dst * scale, noise_bound=0.01 * scale, **kwargs)
    assert ref.certificate is not None and res.certificate is not None
    assert res.certificate.certified == ref.certificate.certified
    assert res.certificate.status == ref.certificate.status
    assert res.certificate.relative_gap == pytest.approx(ref.certificate.relative_gap, rel=1e-3,
                                                         abs=1e-9)
    np.testing.assert_allclose(res.translation / scale, ref.translation, atol=1e-9)


@pytest.mark.parametrize(("kwargs", "exc", "pattern"), [
    ({"time_limit": -1.0}, ValueError, "`time_limit` must be a non-negative finite number"),
    ({"time_limit": True}, TypeError, "`time_limit` must be a number"),
    ({"time_limit": math.nan}, ValueError, "`time_limit`"),
    ({"tol": -1e-3}, ValueError, "`tol`"),
    ({"tol": 0.0}, ValueError, "`tol` must be a positive finite number"),
])
def test_register_rejects_bad_limits(kwargs, exc, pattern):
    src, dst, _, _ = _instance()
    with pytest.raises(exc, match=pattern):
        register(src, dst, noise_bound=0.01, certify=True, **kwargs)
