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


def _rotvec_equal(w, w_ref, atol):
    # At exactly pi, w and -w are the same rotation.
    if np.linalg.norm(w_ref) > np.pi - 1e-6:
        assert np.allclose(w, w_ref, atol=atol) or np.allclose(w, -w_ref, atol=atol)
    else:
        np.testing.assert_allclose(w, w_ref, atol=atol)


@given(st.integers(0, 2**32 - 1))
def test_so3_log_is_scipys_rotation_vector(seed):
    R = _rot_from_seed(seed)
    _rotvec_equal(lie.so3_log(R), Rotation.from_matrix(R).as_rotvec(), 1e-9)


@given(st.one_of(small_vec3, arrays(np.float64, 3, elements=st.floats(-1e-3, 1e-3))))
def test_so3_log_near_identity(w):
    np.testing.assert_allclose(lie.so3_log(lie.so3_exp(w)), w, atol=1e-12)


@given(st.integers(0, 2**32 - 1), st.floats(0.0, 0.12))
def test_so3_log_near_a_half_turn(seed, gap):
    axis = np.random.default_rng(seed).normal(size=3)
    axis /= np.linalg.norm(axis)
    w = axis * (np.pi - gap)
    R = lie.so3_exp(w)
    out = lie.so3_log(R)
    assert np.linalg.norm(out) <= np.pi + 1e-12
    np.testing.assert_allclose(lie.so3_exp(out), R, atol=1e-9)
    _rotvec_equal(out, w, 1e-7)


@given(st.integers(0, 2**32 - 1))
def test_so3_log_batches_over_leading_axes(seed):
    R = Rotation.random(6, random_state=np.random.default_rng(seed)).as_matrix()
    # One of them a half turn, one the identity: the branches mix in one call.
    R[0] = lie.so3_exp([0.0, np.pi, 0.0])
    R[1] = np.eye(3)
    out = lie.so3_log(R.reshape(2, 3, 3, 3))
    assert out.shape == (2, 3, 3)
    for Ri, wi in zip(R, out.reshape(6, 3), strict=True):
        np.testing.assert_allclose(lie.so3_exp(wi), Ri, atol=1e-9)


def test_so3_log_rejects_bad_shapes():
    import pytest

    with pytest.raises(ValueError, match=r"`R` to have shape \(\.\.\., 3, 3\), got \(3, 2\)"):
        lie.so3_log(np.zeros((3, 2)))


@given(st.integers(0, 2**31 - 1))
def test_so3_exp_batch_is_scipys_bits(seed):
    """The compiled batch gives scipy's very numbers (the refinements' poses depend on them):
    angles from 0 (the small-angle series below 1e-3 rad) to past pi."""
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(64, 3)) * rng.choice([0.0, 1e-7, 1e-4, 1e-3, 0.02, 0.3, 1.0, 2.5], size=(64, 1))
    assert np.array_equal(lie.so3_exp_batch(w), Rotation.from_rotvec(w).as_matrix())
    # Non-contiguous input (the columns of a twist) and an empty batch.
    x = rng.normal(scale=0.1, size=(5, 6))
    assert np.array_equal(lie.so3_exp_batch(x[:, 3:]), Rotation.from_rotvec(x[:, 3:]).as_matrix())
    assert lie.so3_exp_batch(np.zeros((0, 3))).shape == (0, 3, 3)
