"""Property tests for the SO(3)/SE(3) helpers, near-identity and near-pi cases included."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from solvers import lie

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
vec3 = arrays(np.float64, 3, elements=st.floats(-3.0, 3.0, allow_nan=False))
small_vec3 = arrays(np.float64, 3, elements=st.floats(-1e-6, 1e-6, allow_nan=False))
twist = arrays(np.float64, 6, elements=st.floats(-3.0, 3.0, allow_nan=False))


def _rot_from_seed(seed: int) -> np.ndarray:
    return lie.random_rotation(np.random.default_rng(seed))


@given(vec3)
def test_hat_vee_roundtrip_and_cross_product(w):
    v = np.array([0.3, -1.2, 2.0])
    np.testing.assert_allclose(lie.hat(w) @ v, np.cross(w, v), atol=1e-12)
    np.testing.assert_allclose(lie.vee(lie.hat(w)), w, atol=1e-12)


@given(st.one_of(vec3, small_vec3))
def test_so3_exp_is_rotation(w):
    R = lie.so3_exp(w)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-10)
    assert np.linalg.det(R) > 0.999999


@given(st.one_of(vec3, small_vec3))
def test_so3_log_inverts_exp(w):
    theta = np.linalg.norm(w)
    if theta > np.pi - 1e-3:  # the log is multi-valued at pi
        w = w / theta * (np.pi - 1e-3)
    np.testing.assert_allclose(lie.so3_log(lie.so3_exp(w)), w, atol=1e-7)


@given(st.integers(0, 2**32 - 1))
def test_so3_exp_log_roundtrip_on_random_rotations(seed):
    R = _rot_from_seed(seed)
    np.testing.assert_allclose(lie.so3_exp(lie.so3_log(R)), R, atol=1e-7)


@given(st.floats(np.pi - 1e-3, np.pi, allow_nan=False), vec3)
def test_so3_log_near_pi(theta, axis):
    if np.linalg.norm(axis) < 1e-3:
        axis = np.array([1.0, 0.0, 0.0])
    axis = axis / np.linalg.norm(axis)
    R = lie.so3_exp(axis * theta)
    np.testing.assert_allclose(lie.so3_exp(lie.so3_log(R)), R, atol=1e-6)
    assert abs(np.linalg.norm(lie.so3_log(R)) - theta) < 1e-6


@given(st.one_of(twist, arrays(np.float64, 6, elements=st.floats(-1e-7, 1e-7))))
def test_se3_log_inverts_exp(xi):
    if np.linalg.norm(xi[3:]) > np.pi - 1e-3:
        xi = xi.copy()
        xi[3:] *= (np.pi - 1e-3) / np.linalg.norm(xi[3:])
    T = lie.se3_exp(xi)
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])
    np.testing.assert_allclose(lie.se3_log(T), xi, atol=1e-7)


@given(st.integers(0, 2**32 - 1), vec3)
def test_invert_transform_and_transform_points(seed, t):
    T = lie.make_transform(_rot_from_seed(seed), t)
    np.testing.assert_allclose(lie.invert_transform(T) @ T, np.eye(4), atol=1e-10)
    p = np.random.default_rng(seed).normal(size=(5, 3))
    homo = (T @ np.c_[p, np.ones(5)].T).T[:, :3]
    np.testing.assert_allclose(lie.transform_points(T, p), homo, atol=1e-10)


@given(st.integers(0, 2**32 - 1), arrays(np.float64, (3, 3), elements=st.floats(-0.05, 0.05)))
def test_project_to_so3_recovers_perturbed_rotation(seed, noise):
    R = _rot_from_seed(seed)
    P = lie.project_to_so3(R + noise)
    np.testing.assert_allclose(P.T @ P, np.eye(3), atol=1e-10)
    assert np.linalg.det(P) > 0
    # The projection is the closest rotation: no farther from R + noise than R itself.
    assert np.linalg.norm(P - (R + noise)) <= np.linalg.norm(R - (R + noise)) + 1e-12


@given(st.integers(0, 2**32 - 1), st.floats(0.0, 179.0))
def test_rotation_error_matches_angle(seed, angle_deg):
    R = _rot_from_seed(seed)
    axis = np.random.default_rng(seed + 1).normal(size=3)
    axis /= np.linalg.norm(axis)
    R2 = R @ lie.so3_exp(axis * np.radians(angle_deg))
    assert abs(lie.rotation_error_deg(R2, R) - angle_deg) < 1e-5
    assert lie.rotation_error_deg(R, R) < 1e-5


@settings(max_examples=30)
@given(st.integers(0, 2**32 - 1))
def test_random_rotation_is_rotation(seed):
    R = _rot_from_seed(seed)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(R) - 1) < 1e-12
