"""Properties of the closed-form weighted Procrustes step."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from solvers import weighted_procrustes
from solvers.lie import make_transform, transform_points

seeds = st.integers(0, 2**32 - 1)


def _instance(seed, n=8):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, 3))
    R, t = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * 2
    w = rng.uniform(0.1, 3.0, n)
    return rng, a, R, t, w


@given(seeds, st.integers(3, 30))
def test_exact_on_noiseless_data(seed, n):
    rng, a, R, t, w = _instance(seed, n)
    b = a @ R.T + t
    Re, te = weighted_procrustes(a, b, w)
    np.testing.assert_allclose(Re, R, atol=1e-8)
    np.testing.assert_allclose(te, t, atol=1e-8)


@given(seeds)
def test_near_identity_pose(seed):
    rng, a, _, _, w = _instance(seed)


    R = Rotation.from_rotvec(rng.normal(size=3) * 1e-7).as_matrix()
    t = rng.normal(size=3) * 1e-8
    Re, te = weighted_procrustes(a, a @ R.T + t, w)
    np.testing.assert_allclose(Re, R, atol=1e-10)
    np.testing.assert_allclose(te, t, atol=1e-10)


@given(seeds)
def test_equivariance_under_target_transform(seed):
    rng, a, R, t, w = _instance(seed)
    b = a @ R.T + t + rng.normal(scale=0.05, size=a.shape)
    Re, te = weighted_procrustes(a, b, w)
    G = make_transform(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
    Rg, tg = weighted_procrustes(a, transform_points(G, b), w)
    np.testing.assert_allclose(make_transform(Rg, tg), G @ make_transform(Re, te), atol=1e-8)


@given(seeds)
def test_invariance_to_permutation(seed):
    rng, a, R, t, w = _instance(seed, 12)
    b = a @ R.T + t + rng.normal(scale=0.05, size=a.shape)
    perm = rng.permutation(12)
    R1, t1 = weighted_procrustes(a, b, w)
    R2, t2 = weighted_procrustes(a[perm], b[perm], w[perm])
    np.testing.assert_allclose(R1, R2, atol=1e-9)
    np.testing.assert_allclose(t1, t2, atol=1e-9)


@settings(max_examples=50)
@given(seeds)
def test_minimises_weighted_squared_error(seed):
    rng, a, R, t, w = _instance(seed)
    b = a @ R.T + t + rng.normal(scale=0.2, size=a.shape)
    Re, te = weighted_procrustes(a, b, w)
    best = w @ np.sum((b - a @ Re.T - te) ** 2, axis=1)


    for _ in range(20):
        # Neither random poses nor small perturbations of the estimate do better.
        near = (Re @ Rotation.from_rotvec(rng.normal(scale=1e-3, size=3)).as_matrix(), te + rng.normal(scale=1e-3, size=3))
        for Rq, tq in ((Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)), near):
            assert w @ np.sum((b - a @ Rq.T - tq) ** 2, axis=1) >= best - 1e-9


@given(seeds)
def test_reflection_is_corrected(seed):
    rng, a, _, _, w = _instance(seed)
    b = a * np.array([1.0, 1.0, -1.0])  # a mirror image: best proper rotation, never det -1
    Re, _ = weighted_procrustes(a, b, w)
    assert np.linalg.det(Re) > 0.999


def test_numba_kernel_agrees_with_numpy(rng):
    from solvers.registration import _kernels

    a = rng.normal(size=(40, 3))
    b = a @ Rotation.random(random_state=rng).as_matrix().T + rng.normal(scale=0.3, size=(40, 3))
    w = rng.uniform(0, 1, 40)
    R1, t1 = weighted_procrustes(a, b, w)
    R2, t2, ok = _kernels.procrustes(a, b, w)
    assert ok
    np.testing.assert_allclose(R1, R2, atol=1e-10)
    np.testing.assert_allclose(t1, t2, atol=1e-10)


def _svd_rotation_objective(a, b, w):
    """tr(R^T H) at the determinant-corrected SVD optimum, and the singular-value scale of H."""
    ca, cb = w @ a / w.sum(), w @ b / w.sum()
    H = ((b - cb) * w[:, None]).T @ (a - ca)
    U, S, Vt = np.linalg.svd(H)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return H, np.trace(R.T @ H), S.sum()


@settings(max_examples=300)
@given(seeds, st.integers(1, 30), st.integers(-4, 4),
       st.sampled_from(["general", "coplanar", "collinear", "reflected", "noise-only"]))
def test_kernel_rotation_matches_corrected_svd(seed, n, log_scale, shape):
    # The kernel's quaternion (Jacobi) rotation reaches the corrected SVD's optimum, including
    # the degenerate shapes where the SVD needs its determinant correction or is not unique.
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, 3)) * 10.0**log_scale
    if shape == "coplanar":
        a[:, 2] = 0.0
    elif shape == "collinear":
        a = np.outer(rng.normal(size=n), rng.normal(size=3)) * 10.0**log_scale
    R = Rotation.random(random_state=rng).as_matrix()
    b = a @ R.T + rng.normal(size=3)
    if shape == "reflected":
        b = b * np.array([1.0, 1.0, -1.0])
    elif shape == "noise-only":
        b = rng.normal(size=(n, 3)) * 10.0**log_scale
    b = b + rng.normal(scale=0.01 * 10.0**log_scale, size=b.shape)
    w = rng.uniform(0.1, 3.0, n)
    Re, te = weighted_procrustes(a, b, w)
    np.testing.assert_allclose(Re.T @ Re, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(Re) - 1.0) < 1e-12
    H, best, scale = _svd_rotation_objective(a, b, w)
    assert np.trace(Re.T @ H) >= best - 1e-12 * max(scale, 1e-300)
    # The translation is the weighted centroid offset for that rotation.
    np.testing.assert_allclose(te, (w @ b - (w @ a) @ Re.T) / w.sum(),
                               atol=1e-12 * (1 + np.abs(b).max()))
