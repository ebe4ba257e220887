"""Validation of the weighted TLS problem and its cost."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from solvers import WeightedTLSProblem


def _pts(n=10, seed=0):
    return np.random.default_rng(seed).normal(size=(n, 3))


def test_cost_matches_definition(rng):
    a, b = _pts(12, 1), _pts(12, 2)
    w = rng.uniform(0, 2, 12)
    beta = rng.uniform(0.1, 1.0, 12)
    p = WeightedTLSProblem(a, b, noise_bound=beta, weights=w, cbar2=2.0)
    R, t = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)
    expected = sum(
        w[k] * min(np.sum((b[k] - R @ a[k] - t) ** 2) / beta[k] ** 2, 2.0) for k in range(12)
    )
    assert p.cost(R, t) == pytest.approx(expected, rel=1e-12)
    assert np.array_equal(p.inliers(R, t), p.residuals_sq(R, t) <= 2.0)


def test_defaults_and_immutability():
    p = WeightedTLSProblem(_pts(), _pts(seed=1), noise_bound=0.1)
    assert np.all(p.weights == 1.0) and p.cbar2 == 1.0
    assert p.noise_bound.shape == (10,)
    with pytest.raises(ValueError):
        p.source[0, 0] = 5.0  # read-only arrays
    with pytest.raises(AttributeError):
        p.cbar2 = 3.0  # type: ignore[misc]


def test_subset_keeps_per_item_data():
    p = WeightedTLSProblem(_pts(), _pts(seed=1), noise_bound=np.arange(1, 11) / 10.0,
                           weights=np.arange(10.0))
    s = p.subset(np.array([1, 3, 5]))
    assert s.n == 3
    np.testing.assert_array_equal(s.weights, [1.0, 3.0, 5.0])
    np.testing.assert_allclose(s.noise_bound, [0.2, 0.4, 0.6])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"source": np.zeros((3, 20))}, r"Expected `source` to have shape \(N, 3\), got \(3, 20\)"),
        ({"target": np.zeros(30)}, r"Expected `target` to have shape \(N, 3\), got \(30,\)"),
        ({"target": np.zeros((9, 3))}, r"same number of rows, got 10 and 9"),
        ({"source": np.zeros((2, 3)), "target": np.zeros((2, 3))}, r"at least 3 correspondences"),
        ({"source": np.zeros((0, 3)), "target": np.zeros((0, 3))}, r"at least 1 points"),
        ({"noise_bound": 0.0}, r"`noise_bound` must be strictly positive"),
        ({"noise_bound": -1.0}, r"`noise_bound` must be strictly positive"),
        ({"noise_bound": np.ones(9)}, r"`noise_bound` to have a scalar or shape \(10,\)"),
        ({"noise_bound": np.nan}, r"`noise_bound` contains NaN"),
        ({"weights": -np.ones(10)}, r"`weights` must be non-negative"),
        ({"weights": np.ones((10, 1))}, r"`weights` to have a scalar or shape \(10,\)"),
        ({"weights": np.full(10, np.inf)}, r"`weights` contains NaN or inf"),
        ({"cbar2": 0.0}, r"`cbar2` must be a positive"),
        ({"cbar2": [1.0, 2.0]}, r"`cbar2` must be a positive"),
        ({"cbar2": float("inf")}, r"`cbar2` must be a positive finite"),
        ({"cbar2": float("nan")}, r"`cbar2` must be a positive finite"),
        ({"weights": -1.0}, r"`weights` must be non-negative"),
        ({"noise_bound": float("inf")}, r"`noise_bound` contains NaN"),
        ({"source": np.vstack([np.full((1, 3), np.nan), np.zeros((9, 3))])},
         r"`source` contains NaN or inf values in 1 row"),
        ({"target": np.vstack([np.full((2, 3), -np.inf), np.zeros((8, 3))])},
         r"`target` contains NaN or inf values in 2 row"),
    ],
)
@pytest.mark.parametrize("make", ["problem", "unit_scale_problem"])
def test_bad_input_raises_value_error(kwargs, match, make):
    from solvers.registration import unit_scale_problem

    args = {"source": _pts(), "target": _pts(seed=1), "noise_bound": 0.1}
    args.update(kwargs)
    src, dst = args.pop("source"), args.pop("target")
    with pytest.raises(ValueError, match=match):
        (WeightedTLSProblem if make == "problem" else unit_scale_problem)(src, dst, **args)


def test_nan_points_raise():
    a = _pts()
    a[3, 1] = np.nan
    with pytest.raises(ValueError, match=r"`source` contains NaN or inf values in 1 row"):
        WeightedTLSProblem(a, _pts(seed=1), noise_bound=0.1)
    b = _pts()
    b[0, 0] = np.inf
    with pytest.raises(ValueError, match=r"`target` contains NaN or inf"):
        WeightedTLSProblem(_pts(), b, noise_bound=0.1)


@pytest.mark.parametrize(
    "bad", [[["a", "b", "c"]] * 4, np.array([[1, 2, 3]] * 4, dtype=object), [[1j, 2, 3]] * 4, "xyz"]
)
def test_non_numeric_raises_type_error(bad):
    with pytest.raises(TypeError, match="`source`"):
        WeightedTLSProblem(bad, _pts(4), noise_bound=0.1)


def test_missing_noise_bound_is_an_error():
    with pytest.raises(ValueError, match="`noise_bound` is required"):
        WeightedTLSProblem(_pts(), _pts(seed=1), noise_bound=None)  # type: ignore[arg-type]


def test_pickle_roundtrip():
    import pickle

    p = WeightedTLSProblem(_pts(), _pts(seed=1), noise_bound=0.1, weights=np.arange(10.0))
    q = pickle.loads(pickle.dumps(p))
    np.testing.assert_array_equal(q.weights, p.weights)
    np.testing.assert_array_equal(q.source, p.source)


def test_residuals_of_two_translations_match_one_at_a_time(rng):
    a = rng.normal(size=(30, 3))
    b = rng.normal(size=(30, 3))
    problem = WeightedTLSProblem(a, b, noise_bound=rng.uniform(0.1, 1.0, 30))
    R = Rotation.random(random_state=1).as_matrix()
    t1, t2 = rng.normal(size=3), rng.normal(size=3)
    r1, r2 = problem.residuals_sq_pair(R, t1, t2)
    np.testing.assert_allclose(r1, problem.residuals_sq(R, t1), rtol=1e-12)
    np.testing.assert_allclose(r2, problem.residuals_sq(R, t2), rtol=1e-12)
    assert not np.allclose(r1, r2)


@settings(max_examples=60, deadline=None)
@given(exponent=st.integers(-200, 200), n=st.integers(3, 40), seed=st.integers(0, 2**16),
       scalar_noise=st.booleans(), with_weights=st.booleans())
def test_unit_scale_problem_is_scaling_a_validated_problem(exponent, n, seed, scalar_noise,
                                                           with_weights):
    # register's one-pass path (validate, then scale the copies in place) against the two
    # steps it replaces: the same arrays bit for bit, the same scale, the same cached flags.
    from solvers.registration import to_unit_scale, unit_scale_problem

    rng = np.random.default_rng(seed)
    s = 10.0**exponent
    a, b = rng.normal(size=(n, 3)) * s, rng.normal(size=(n, 3)) * s
    beta = 0.05 * s if scalar_noise else rng.uniform(0.01, 0.1, n) * s
    w = rng.uniform(0.0, 2.0, n) if with_weights else None
    ref, ref_scale = to_unit_scale(WeightedTLSProblem(a, b, noise_bound=beta, weights=w))
    unit, scale = unit_scale_problem(a, b, noise_bound=beta, weights=w)
    assert scale == ref_scale
    for name in ("source", "target", "noise_bound", "weights"):
        got, want = getattr(unit, name), getattr(ref, name)
        assert np.array_equal(got, want) and not got.flags.writeable, name
    fresh = WeightedTLSProblem(unit.source, unit.target, noise_bound=unit.noise_bound,
                               weights=unit.weights)
    assert unit._uniform_weights == fresh._uniform_weights == (w is None)
    assert unit._uniform_noise == fresh._uniform_noise
    assert to_unit_scale(unit) == (unit, 1.0)


def test_problem_fields_are_read_only_views_the_caller_cannot_reach():
    src = np.random.default_rng(0).normal(size=(5, 3))
    p = WeightedTLSProblem(src, src + 1.0, noise_bound=0.1)
    src[0, 0] = 99.0  # the problem holds its own copy
    assert p.source[0, 0] != 99.0
    with pytest.raises(ValueError, match="read-only"):
        p.source[0, 0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        p.weights[0] = 2.0


def test_from_unit_scale_scales_the_poses_recorded_in_info() -> None:
    """A replaced candidate's pose (and one a certificate dictionary records) comes back in the
    caller's units like the result's own pose; other entries are untouched."""
    from solvers import RegistrationResult, SolverStatus
    from solvers.registration import from_unit_scale

    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    info = {"candidate_T_target_source": T.tolist(), "candidate_cost": 2.5,
            "rotation_certificate": {"pose_T_target_source": T.tolist(), "gap": 1e-4}}
    res = RegistrationResult(T_target_source=T, inliers=np.ones(3, bool), cost=1.0,
                             iterations=1, solve_time=0.0, status=SolverStatus.CONVERGED, message="",
                             info=info)
    out = from_unit_scale(res, 10.0)
    assert np.allclose(out.translation, [1.0, -2.0, 3.0])
    cand = np.asarray(out.info["candidate_T_target_source"])
    assert np.allclose(cand[:3, 3], [1.0, -2.0, 3.0]) and np.allclose(cand[:3, :3], np.eye(3))
    assert isinstance(out.info["candidate_T_target_source"], list)
    assert np.allclose(np.asarray(out.info["rotation_certificate"]["pose_T_target_source"])[:3, 3],
                       [1.0, -2.0, 3.0])
    assert out.info["candidate_cost"] == 2.5 and out.info["rotation_certificate"]["gap"] == 1e-4
    assert np.allclose(np.asarray(res.info["candidate_T_target_source"])[:3, 3], [0.1, -0.2, 0.3])
