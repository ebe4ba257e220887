"""Property tests for the SO(3)/SE(3) helpers, near-identity and near-pi cases included."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from solvers import lie

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
vec3 = arrays(np.float64, 3, elements=st.floats(-3.0, 3.0, allow_nan=False))
small_vec3 = arrays(np.float64, 3, elements=st.floats(-1e-6, 1e-6, allow_nan=False))
twist = arrays(np.float64, 6, elements=st.floats(-3.0, 3.0, allow_nan=False))


def _rot_from_seed(seed: int) -> np.ndarray:
    return Rotation.random(random_state=np.random.default_rng(seed)).as_matrix()


@given(st.one_of(vec3, small_vec3))
def test_so3_exp_is_scipys_rotation_vector(w):
    R = lie.so3_exp(w)
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-15)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-10)


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
    R2 = R @ Rotation.from_rotvec(axis * np.radians(angle_deg)).as_matrix()
    assert abs(lie.rotation_error_deg(R2, R) - angle_deg) < 1e-5
    assert lie.rotation_error_deg(R, R) < 1e-5
