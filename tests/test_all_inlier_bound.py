"""The all-inlier closed-form bound (solvers.certify.all_inliers) against exhaustive
enumeration, and its use by the full-problem certificate."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from solvers import solve_registration
from solvers.certify import certify_result
from solvers.certify.all_inliers import all_inlier_bound, horn_matrix, quaternion_rotation
from solvers.problem import WeightedTLSProblem
from tests.test_certify_audit import exact_optimum


def test_horn_matrix_quadratic_form_is_the_rotated_inner_product() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        a, b = rng.normal(size=(6, 3)), rng.normal(size=(6, 3))
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = quaternion_rotation(q)
        assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        assert q @ horn_matrix(a.T @ b) @ q == pytest.approx(np.sum((a @ R.T) * b), rel=1e-12)


def _instance(rng: np.random.Generator) -> WeightedTLSProblem:
    k = int(rng.integers(4, 13))
    src = rng.uniform(-1, 1, (k, 3))
    R = Rotation.random(random_state=rng).as_matrix()
    sigma = rng.choice([0.005, 0.01, 0.02, 0.04])
    dst = src @ R.T + rng.normal(size=3) + sigma * rng.normal(size=(k, 3))
    return WeightedTLSProblem(src, dst, noise_bound=0.0554 * rng.uniform(0.5, 2, k),
                              weights=rng.uniform(0.3, 3, k), cbar2=float(rng.choice([0.5, 1, 2])))


def test_bound_never_exceeds_the_enumerated_minimum_and_is_exact_when_it_says_so() -> None:
    """400 instances (K = 4-12, uneven weights and noise bounds, cbar2 0.5-2, noise up to
    0.7 beta): no bound above the exact minimum; an ``exact`` bound is that minimum."""
    rng = np.random.default_rng(1)
    used = exact = 0
    for _ in range(400):
        p = _instance(rng)
        bound = all_inlier_bound(p)
        if bound is None:
            continue
        used += 1
        opt = exact_optimum(p)
        assert bound.lower <= opt + 1e-12 * (1 + opt)
        assert bound.cost >= opt - 1e-9 * (1 + opt)
        if bound.exact:
            exact += 1
            assert bound.lower == pytest.approx(opt, rel=1e-8, abs=1e-10)
    assert used >= 100 and exact >= 80


def test_none_when_a_term_is_outside_the_noise_bound() -> None:
    rng = np.random.default_rng(2)
    src = rng.uniform(-1, 1, (10, 3))
    dst = src.copy()
    dst[0] += 1.0
    assert all_inlier_bound(WeightedTLSProblem(src, dst, noise_bound=0.05)) is None


def test_full_certificate_of_an_all_inlier_clique_is_closed_form() -> None:
    """N = 100 without outliers (the branch and bound took millions of nodes): certified with
    no branch-and-bound node."""
    from tests.conftest import make_instance

    src, dst, *_ = make_instance(np.random.default_rng(3), 100, 0.0)
    p = WeightedTLSProblem(src, dst, noise_bound=5.54 * 0.01)
    cert = certify_result(p, solve_registration(p)).certificate
    assert cert.certified, cert.message
    assert "all-inlier closed form" in cert.backend_status and "0 nodes" in cert.backend_status
