"""Bad and hostile inputs through the public API: a clear error naming the argument, never a
silent wrong result (a number computed from a non-rotation, a mask cast to coordinates)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from certpose.api import register
from solvers import WeightedTLSProblem, lie, solve_gnc, solve_pruned, solve_registration

EYE = np.eye(3)
R0 = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
T0 = lie.make_transform(R0, [1.0, 2.0, 3.0])
NAN3 = np.full((3, 3), np.nan)
REFLECTION = np.diag([1.0, 1.0, -1.0])
SHEAR = np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def _transform(M: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = M
    return T


BAD_ROTATIONS = {
    "2I": 2 * EYE, "zeros": np.zeros((3, 3)), "reflection": REFLECTION, "shear": SHEAR,
    "nan": NAN3, "inf": np.full((3, 3), np.inf), "ones": np.ones((3, 3)), "half": 0.5 * R0,
    "bool": EYE.astype(bool), "shape_2x2": np.eye(2), "shape_4x4": np.eye(4),
    "shape_9": np.eye(3).ravel(), "text": "identity", "none": None, "dict": {"R": EYE},
    "complex": EYE.astype(complex), "object": np.array([[EYE]], dtype=object), "ragged": [[1, 0], [0]],
}
BAD_TRANSFORMS = {
    "diag2221": np.diag([2.0, 2.0, 2.0, 1.0]), "reflection": _transform(REFLECTION),
    "shear": _transform(SHEAR), "last_row": np.vstack([T0[:3], [1.0, 0.0, 0.0, 1.0]]),
    "nan": np.full((4, 4), np.nan), "zeros": np.zeros((4, 4)), "shape_3x4": T0[:3],
    "shape_3x3": EYE, "bool": np.eye(4, dtype=bool), "text": "T", "dict": {"T": T0},
}


@pytest.mark.parametrize("name", BAD_ROTATIONS)
@pytest.mark.parametrize("fn", [lie.so3_log, lie.rotation_angle_deg,
                                lambda R: lie.rotation_error_deg(R, EYE),
                                lambda R: lie.rotation_error_deg(EYE, R),
                                lambda R: lie.make_transform(R, [0.0, 0.0, 0.0])],
                         ids=["so3_log", "rotation_angle_deg", "rotation_error_deg_est",
                              "rotation_error_deg_gt", "make_transform"])
def test_rotation_inputs_are_refused(fn, name):
    with pytest.raises((ValueError, TypeError), match=r"`(R|R_est|R_gt|rotation)`"):
        fn(BAD_ROTATIONS[name])


@pytest.mark.parametrize("name", BAD_TRANSFORMS)
@pytest.mark.parametrize("fn", [lie.invert_transform, lie.se3_log,
                                lambda T: lie.transform_points(T, np.zeros((2, 3)))],
                         ids=["invert_transform", "se3_log", "transform_points"])
def test_transform_inputs_are_refused(fn, name):
    with pytest.raises((ValueError, TypeError), match=r"`T"):
        fn(BAD_TRANSFORMS[name])


def test_the_issues_lie_cases():
    """Each once returned a number: so3_log(2I) zero, the error of 2I against EYE zero degrees,
    diag(2, 2, 2, 1) a wrong inverse, zeros the identity, ones a non-rigid transform."""
    with pytest.raises(ValueError, match="not a rotation matrix"):
        lie.so3_log(2 * EYE)
    with pytest.raises(ValueError, match="`R_est` is not a rotation matrix"):
        lie.rotation_error_deg(2 * EYE, EYE)
    with pytest.raises(ValueError, match="`T\\[:3, :3\\]` is not a rotation matrix"):
        lie.invert_transform(np.diag([2.0, 2.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="`M` has rank below 2"):
        lie.project_to_so3(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="`rotation` is not a rotation matrix"):
        lie.make_transform(np.ones((3, 3)), [0.0, 0.0, 0.0])


@pytest.mark.parametrize("M", [np.zeros((3, 3)), np.outer([1.0, 2.0, 3.0], [0.0, 1.0, 0.0]),
                               np.full((3, 3), np.nan), np.eye(2), np.ones((3, 3)),
                               EYE.astype(bool), "M"],
                         ids=["zeros", "rank1", "nan", "2x2", "ones_rank1", "bool", "text"])
def test_project_to_so3_refuses_matrices_without_a_closest_rotation(M):
    with pytest.raises((ValueError, TypeError), match="`M`"):
        lie.project_to_so3(M)


@pytest.mark.parametrize("value", [np.zeros(2), np.zeros(4), np.zeros((1, 3)), [np.nan, 0, 0],
                                   [np.inf, 0, 0], "abc", None, np.array([True, False, True])],
                         ids=["len2", "len4", "row", "nan", "inf", "text", "none", "bool"])
@pytest.mark.parametrize("fn", [lie.so3_exp, lambda v: lie.make_transform(EYE, v),
                                lambda v: lie.translation_error(v, np.zeros(3)),
                                lambda v: lie.translation_error(np.zeros(3), v)],
                         ids=["so3_exp", "make_transform_t", "translation_error_est",
                              "translation_error_gt"])
def test_vector_inputs_are_refused(fn, value):
    with pytest.raises((ValueError, TypeError), match=r"`(omega|translation|t_est|t_gt)`"):
        fn(value)


@pytest.mark.parametrize("xi", [np.zeros(5), np.zeros((2, 6)), np.full(6, np.nan), "xi"],
                         ids=["len5", "2x6", "nan", "text"])
def test_se3_exp_refuses_bad_twists(xi):
    with pytest.raises((ValueError, TypeError), match="`xi`"):
        lie.se3_exp(xi)


@pytest.mark.parametrize("omegas", [np.zeros(3), np.zeros((2, 4)), np.full((2, 3), np.inf)],
                         ids=["flat", "2x4", "inf"])
def test_so3_exp_batch_refuses_bad_shapes(omegas):
    with pytest.raises(ValueError, match="`omegas`"):
        lie.so3_exp_batch(omegas)


def test_rotation_inputs_within_float32_rounding_pass():
    """Rotations stored as float32 (ground-truth files) are rotations to ~1e-7: accepted."""
    R32 = R0.astype(np.float32)
    assert lie.rotation_error_deg(R32, R0) < 0.05  # arccos near 1: sqrt of the rounding
    np.testing.assert_allclose(lie.so3_log(R32), Rotation.from_matrix(R0).as_rotvec(), atol=1e-6)


# --- registration ---------------------------------------------------------------------------

def _pair(n: int = 30, seed: int = 0):
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(n, 3))
    return src, src @ R0.T + 0.5


BAD_POINTS = {
    "bool": lambda s: s > 0, "int_ok_but_shape": lambda s: s[:, :2].astype(int),
    "transposed": lambda s: s.T, "flat": lambda s: s.ravel(), "3d": lambda s: s[None],
    "nan": lambda s: np.where(s > 2, np.nan, s), "inf": lambda s: np.where(s > 2, np.inf, s),
    "complex": lambda s: s.astype(complex), "text": lambda s: "points.ply",
    "dict": lambda s: {"points": s}, "none": lambda s: None, "strings": lambda s: s.astype(str),
    "object": lambda s: s.astype(object).tolist() + [["a", "b", "c"]], "empty": lambda s: s[:0],
    "too_few": lambda s: s[:2], "rows_differ": lambda s: s[:-1],
}


@pytest.mark.parametrize("case", BAD_POINTS)
@pytest.mark.parametrize("which", ["source", "target"])
def test_register_refuses_bad_points(case, which):
    src, dst = _pair()
    bad = BAD_POINTS[case](src if which == "source" else dst)
    args = (bad, dst) if which == "source" else (src, bad)
    with pytest.raises((ValueError, TypeError), match=r"`(source|target)`|correspondences"):
        register(*args, noise_bound=0.01)


def test_register_refuses_boolean_masks_the_issues_case():
    """register(src > 0, dst > 0) once cast the masks to 0/1 and reported success."""
    rng = np.random.default_rng(0)
    src, dst = rng.normal(size=(100, 3)), rng.normal(size=(100, 3))
    with pytest.raises(TypeError, match="`source` must be a numeric array, got dtype bool"):
        register(src > 0, dst > 0, noise_bound=0.1)


BAD_NOISE = {"zero": 0.0, "negative": -0.1, "nan": np.nan, "inf": np.inf, "bool": True,
             "bool_array": np.ones(30, dtype=bool), "wrong_len": np.full(29, 0.1),
             "text": "0.1", "none": None, "complex": 0.1 + 0j, "dict": {"beta": 0.1},
             "2d": np.full((30, 1), 0.1)}


@pytest.mark.parametrize("case", BAD_NOISE)
def test_register_refuses_bad_noise_bounds(case):
    src, dst = _pair()
    with pytest.raises((ValueError, TypeError), match="`noise_bound`"):
        register(src, dst, noise_bound=BAD_NOISE[case])


BAD_OPTIONS = {
    "weights_negative": dict(weights=-np.ones(30)), "weights_len": dict(weights=np.ones(3)),
    "weights_nan": dict(weights=np.full(30, np.nan)), "weights_text": dict(weights="ones"),
    "cbar2_zero": dict(cbar2=0.0), "cbar2_neg": dict(cbar2=-1.0), "cbar2_nan": dict(cbar2=np.nan),
    "cbar2_vec": dict(cbar2=np.ones(2)), "solver": dict(solver="teaser"),
    "prune": dict(prune="sometimes"), "scope": dict(scope="everything"),
    "tol_zero": dict(tol=0.0), "tol_neg": dict(tol=-1.0), "tol_text": dict(tol="1e-3"),
    "time_limit_neg": dict(time_limit=-1.0), "time_limit_nan": dict(time_limit=float("nan")),
    "time_limit_bool": dict(time_limit=True),
}


@pytest.mark.parametrize("case", BAD_OPTIONS)
def test_register_refuses_bad_options(case):
    src, dst = _pair()
    kwargs = BAD_OPTIONS[case]
    name = next(iter(kwargs))
    with pytest.raises((ValueError, TypeError), match=f"`{name}`"):
        register(src, dst, noise_bound=0.01, **kwargs)


@pytest.mark.parametrize("problem", [{"source": 1}, None, "problem", np.zeros((3, 3)),
                                     [np.zeros((3, 3)), np.zeros((3, 3))]],
                         ids=["dict", "none", "text", "array", "list"])
@pytest.mark.parametrize("fn", [solve_registration, solve_gnc, solve_pruned],
                         ids=["solve_registration", "solve_gnc", "solve_pruned"])
def test_solvers_refuse_what_is_not_a_problem(fn, problem):
    with pytest.raises(TypeError, match="Expected `problem` to be a WeightedTLSProblem, got"):
        fn(problem)


def test_problem_refuses_boolean_points():
    src, dst = _pair()
    with pytest.raises(TypeError, match="`target` must be a numeric array, got dtype bool"):
        WeightedTLSProblem(src, dst > 0, noise_bound=0.1)


def test_huge_noise_bound_message_is_in_the_callers_units():
    """noise_bound=1e9 was reported as "noise bound 5e+08" (the unit-scale problem's)."""
    src, dst = _pair(50)
    res = register(src, dst, noise_bound=1e9)
    assert not res.success
    assert "5e+08" not in res.message and "2.5e+08" not in res.message
    assert "noise bound" in res.message


# --- RGB-D input ----------------------------------------------------------------------------

@pytest.fixture()
def depth_png(tmp_path):
    import imageio.v3 as iio

    path = tmp_path / "depth.png"
    iio.imwrite(path, np.full((48, 64), 1000, dtype=np.uint16))
    return path


@pytest.mark.parametrize("intrinsics, match", [
    ({"fx": 1}, "missing fy, cx, cy"),
    ({"fx": 50, "fy": 50, "cx": 32, "cy": 24, "k1": 0.1}, "unknown k1"),
    ([50.0, 50.0, 32.0], "got 3 value"),
    ("50 50 32 24", "numeric"),
    (np.array([True, True, True, True]), "bool"),
    ([50.0, 50.0, np.nan, 24.0], "finite"),
    ([-50.0, 50.0, 32.0, 24.0], "positive"),
], ids=["dict_missing", "dict_extra", "three", "text", "bool", "nan", "negative_fx"])
def test_load_rgbd_intrinsics_messages(depth_png, intrinsics, match):
    from certpose.geometry.rgbd import load_rgbd

    with pytest.raises((ValueError, TypeError), match=match):
        load_rgbd(None, depth_png, intrinsics)


def test_load_rgbd_takes_a_mapping_of_intrinsics(depth_png):
    from certpose.geometry.rgbd import load_rgbd

    frame = load_rgbd(None, depth_png, {"fx": 50.0, "fy": 51.0, "cx": 32.0, "cy": 24.0})
    assert (frame.intrinsics.fx, frame.intrinsics.fy, frame.intrinsics.width) == (50.0, 51.0, 64)


# --- the command line: exit 2 and one line naming the option, never a traceback ---------------

@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli_inputs")
    src, dst = _pair(30)
    np.save(d / "src.npy", src)
    np.save(d / "dst.npy", dst)
    np.save(d / "src_bool.npy", src > 0)
    np.save(d / "src_2col.npy", src[:, :2])
    np.save(d / "src_short.npy", src[:20])
    np.save(d / "src_nan.npy", np.where(src > 2, np.nan, src))
    np.save(d / "w_neg.npy", -np.ones(30))
    np.save(d / "w_len.npy", np.ones(3))
    (d / "text.png").write_text("hello\n")
    (d / "garbage.npy").write_bytes(b"\x00\x01garbage")
    (d / "empty.csv").write_text("")
    (d / "words.csv").write_text("a,b,c\nd,e,f\n")
    (d / "dir.npy").mkdir()
    return d


CLI_CASES = {
    "tol_negative": (["register", "{d}/src.npy", "{d}/dst.npy", "--noise-bound", "0.01",
                      "--certify", "--tol", "-1"], "`tol` must be a positive finite number"),
    "tol_zero": (["register", "{d}/src.npy", "{d}/dst.npy", "--noise-bound", "0.01",
                  "--certify", "--tol", "0"], "`tol` must be a positive finite number"),
    "tol_nan": (["register", "{d}/src.npy", "{d}/dst.npy", "--noise-bound", "0.01",
                 "--certify", "--tol", "nan"], "`tol`"),
    "noise_zero": (["register", "{d}/src.npy", "{d}/dst.npy", "--noise-bound", "0"],
                   "noise_bound"),
    "noise_negative": (["register", "{d}/src.npy", "{d}/dst.npy", "--noise-bound", "-1"],
                       "noise"),
    "noise_inf": (["register", "{d}/src.npy", "{d}/dst.npy", "--noise-bound", "inf"], "noise"),
    "noise_text": (["register", "{d}/src.npy", "{d}/dst.npy", "--noise-bound", "abc"],
                   "--noise-bound"),
    "noise_missing": (["register", "{d}/src.npy", "{d}/dst.npy"], "--noise-bound"),
    "bool_points": (["register", "{d}/src_bool.npy", "{d}/dst.npy", "--noise-bound", "0.01"],
                    "bool"),
    "two_columns": (["register", "{d}/src_2col.npy", "{d}/dst.npy", "--noise-bound", "0.01"],
                    "(N, 3)"),
    "rows_differ": (["register", "{d}/src_short.npy", "{d}/dst.npy", "--noise-bound", "0.01"],
                    "row k of each must correspond"),
    "nan_points": (["register", "{d}/src_nan.npy", "{d}/dst.npy", "--noise-bound", "0.01"],
                   "NaN"),
    "missing_file": (["register", "{d}/none.npy", "{d}/dst.npy", "--noise-bound", "0.01"],
                     "none.npy"),
    "garbage_npy": (["register", "{d}/garbage.npy", "{d}/dst.npy", "--noise-bound", "0.01"],
                    "garbage.npy"),
    "empty_csv": (["register", "{d}/empty.csv", "{d}/dst.npy", "--noise-bound", "0.01"],
                  "empty.csv"),
    "words_csv": (["register", "{d}/words.csv", "{d}/dst.npy", "--noise-bound", "0.01"],
                  "words.csv"),
    "dir_as_file": (["register", "{d}/dir.npy", "{d}/dst.npy", "--noise-bound", "0.01"],
                    "dir.npy"),
    "weights_negative": (["register", "{d}/src.npy", "{d}/dst.npy", "--noise-bound", "0.01",
                          "--weights", "{d}/w_neg.npy"], "weights"),
    "weights_length": (["register", "{d}/src.npy", "{d}/dst.npy", "--noise-bound", "0.01",
                        "--weights", "{d}/w_len.npy"], "weights"),
    "time_limit_negative": (["register", "{d}/src.npy", "{d}/dst.npy", "--noise-bound", "0.01",
                             "--certify", "--time-limit", "-5"], "time_limit"),
    "json_into_dir": (["register", "{d}/src.npy", "{d}/dst.npy", "--noise-bound", "0.01",
                       "--json", "{d}/dir.npy"], "directory"),
    "json_no_folder": (["register", "{d}/src.npy", "{d}/dst.npy", "--noise-bound", "0.01",
                        "--json", "{d}/nofolder/out.json"], "does not exist"),
    "demo_outliers": (["register", "--demo", "--demo-outliers", "1.5"], "--demo-outliers"),
    "demo_n": (["register", "--demo", "--demo-n", "2"], "--demo-n"),
    "demo_noise": (["register", "--demo", "--demo-noise", "nan"], "--demo-noise"),
    "seed_negative": (["register", "--demo", "--seed", "-3"], "non-negative"),
    "unknown_solver": (["register", "--demo", "--solver", "teaser"], "invalid choice"),
    "rgbd_text_png": (["pose", "--rgbd", "-", "{d}/text.png", "--intrinsics", "40", "40", "20",
                       "15", "--model", "{d}/src.npy", "--mask", "{d}/text.png"],
                      "not a PNG file"),
    "pose_voxel_negative": (["pose", "--demo", "--voxel-size", "-1"], "--voxel-size"),
    "pose_samples_negative": (["pose", "--demo", "--samples", "-1"], "--samples"),
    "pose_certify_modes_negative": (["pose", "--demo", "--certify-modes", "-1"],
                                    "--certify-modes"),
    "pose_mode_margin_alone": (["pose", "--demo", "--mode-margin", "0.05"],
                               "--mode-margin needs --certify-modes"),
    "pose_mode_margin_negative": (["pose", "--demo", "--certify-modes", "--mode-margin", "-0.1"],
                                  "--mode-margin"),
    "pose_particles_no_samples": (["pose", "--demo", "--particles", "{d}/p.npz"],
                                  "--particles needs --samples"),
    "bench_trials_zero": (["bench", "--trials", "0", "--no-dask"], "--trials"),
    "bench_unknown_solver": (["bench", "--solvers", "nope", "--no-dask"], "nope"),
    "object_no_source": (["object", "build", "-o", "{d}/m.npz"], "--ycbv"),
}


@pytest.mark.parametrize("case", CLI_CASES)
def test_cli_bad_input_is_one_line_exit_2(files, capsys, case):
    from certpose.cli import main

    argv, message = CLI_CASES[case]
    argv = [a.format(d=files) for a in argv]
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, (case, err)
    assert "Traceback" not in err
    assert message in err, (case, err)


# --- properties: what is refused and what passes --------------------------------------------

@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.5, 2.0).filter(lambda s: abs(s - 1) > 1e-3))
def test_scaled_rotations_are_refused_everywhere(seed, s):
    R = Rotation.random(random_state=np.random.default_rng(seed)).as_matrix()
    for fn in (lie.so3_log, lie.rotation_angle_deg, lambda M: lie.rotation_error_deg(M, R),
               lambda M: lie.make_transform(M, np.zeros(3)),
               lambda M: lie.invert_transform(_transform(M))):
        with pytest.raises(ValueError, match="not a rotation matrix"):
            fn(s * R)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.0, 1e-9))
def test_rotations_near_identity_and_rounded_ones_pass(seed, angle):
    """Near the identity (the small-angle branch) and with rounding noise of 1e-9."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    R = Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix()
    noisy = R + 1e-9 * rng.normal(size=(3, 3))
    assert lie.rotation_angle_deg(noisy) < 1e-2
    np.testing.assert_allclose(lie.so3_log(R), Rotation.from_matrix(R).as_rotvec(), atol=1e-12)
    np.testing.assert_allclose(lie.invert_transform(lie.make_transform(noisy, np.ones(3)))[:3, 3],
                               -noisy.T @ np.ones(3), atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_project_to_so3_then_strict_helpers_accept(seed):
    """Whatever full-rank matrix is projected, the helpers take the projection."""
    M = np.random.default_rng(seed).normal(size=(3, 3))
    R = lie.project_to_so3(M)
    assert lie.rotation_error_deg(R, R) < 1e-4
    lie.so3_log(R)


def test_so3_log_unchecked_is_the_same_numbers_and_still_checks_the_shape():
    R = Rotation.random(50, random_state=np.random.default_rng(1)).as_matrix()
    np.testing.assert_array_equal(lie.so3_log(R, check=False), lie.so3_log(R))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3, 3\)"):
        lie.so3_log(np.eye(4), check=False)
