"""Full-problem dual certificates (solvers.certify.joint_dual): soundness, tightness, refusals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from solvers import solve_registration
from solvers.certificate import relative_gap
from solvers.certify.joint_dual import (
    JointAffineProjector,
    initial_dual,
    joint_candidate,
    joint_dual_certificate,
)
from solvers.problem import WeightedTLSProblem
from tests.conftest import make_instance
from tests.test_certify import full_optimum


def _random_problem(rng: np.random.Generator, k: int, n_out: int, varied: bool) -> WeightedTLSProblem:
    src, dst, *_ = make_instance(rng, k, n_out / k)
    beta = 0.0554 * (rng.uniform(0.7, 1.5, k) if varied else np.ones(k))
    w = rng.uniform(0.3, 2.0, k) if varied else None
    c2 = float(rng.uniform(0.5, 2.0)) if varied else 1.0
    return WeightedTLSProblem(src, dst, noise_bound=beta, weights=w, cbar2=c2)


def test_projection_is_exact_and_initial_point_is_stationary() -> None:
    """The closed-form projection is idempotent, orthogonal, and enforces S x = 0."""
    rng = np.random.default_rng(0)
    p = _random_problem(rng, 6, 2, varied=True)
    _, lift, x = joint_candidate(p, Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
    proj = JointAffineProjector(lift, x)
    G = rng.normal(size=(x.size, x.size))
    G = G + G.T
    S = proj.project(G)
    S0 = initial_dual(lift, x)
    scale = np.abs(G).max()
    assert np.abs(S @ x).max() <= 1e-9 * scale
    assert np.abs(proj.project(S) - S).max() <= 1e-9 * scale
    # Orthogonality against another point of the affine set (the closed-form initial point).
    assert abs(np.sum((G - S) * (S0 - S))) <= 1e-9 * np.linalg.norm(G - S) * np.linalg.norm(S0 - S)
    assert np.abs(S0 @ x).max() <= 1e-9 * np.abs(S0).max()
    assert np.abs(proj.project(S0) - S0).max() <= 1e-9 * np.abs(S0).max()


def test_candidate_change_of_variables_keeps_the_cost() -> None:
    rng = np.random.default_rng(1)
    p = _random_problem(rng, 7, 3, varied=True)
    R, t = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)
    pid, lift, x = joint_candidate(p, R, t)
    assert pid.cost(np.eye(3), np.zeros(3)) == pytest.approx(p.cost(R, t), rel=1e-10)
    assert float(x @ lift.dense_cost() @ x) == pytest.approx(p.cost(R, t), rel=1e-8, abs=1e-10)


def test_soundness_against_exhaustive_search() -> None:
    """K <= 6 with outliers, good and random candidates, early stops: bound <= optimum."""
    rng = np.random.default_rng(2)
    with threadpool_limits(1):
        for i in range(12):
            k = int(rng.integers(4, 7))
            p = _random_problem(rng, k, int(rng.integers(0, k - 2)), varied=i % 2 == 0)
            opt = full_optimum(p)
            if i % 3:
                res = solve_registration(p)
                R, t = res.rotation, res.translation
            else:
                R, t = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)
            out = joint_dual_certificate(p, R, t, max_iterations=int(rng.integers(0, 100)))
            scale = 1.0 + p.cbar2 * p.weights.sum()
            assert out.lower_bound <= opt + 1e-6 * scale, (i, out, opt)
            assert out.upper_bound == pytest.approx(p.cost(R, t), rel=1e-7, abs=1e-9)


@pytest.mark.parametrize(("k", "n_out", "sigma"), [(6, 0, 0.0), (6, 0, 0.01), (5, 1, 0.01)])
def test_certifies_noiseless_and_low_outlier_instances(k: int, n_out: int, sigma: float) -> None:
    rng = np.random.default_rng(3 + n_out)
    src, dst, R, t, _ = make_instance(rng, k, n_out / k, sigma=sigma)
    p = WeightedTLSProblem(src, dst, noise_bound=0.0554)
    res = solve_registration(p)
    with threadpool_limits(1):
        out = joint_dual_certificate(p, res.rotation, res.translation, tol=1e-3, time_limit=20)
    opt = full_optimum(p)
    assert out.converged
    assert relative_gap(p.cost(res.rotation, res.translation), out.lower_bound) <= 1e-3
    assert out.lower_bound <= opt + 1e-6 * (1 + p.n)


def test_rotated_candidate_is_not_certified() -> None:
    rng = np.random.default_rng(4)
    src, dst, *_ = make_instance(rng, 6, 1 / 6)
    p = WeightedTLSProblem(src, dst, noise_bound=0.0554)
    res = solve_registration(p)
    R_bad = Rotation.from_rotvec(np.radians(10.0) * np.array([0.0, 0.0, 1.0])).as_matrix() @ res.rotation
    with threadpool_limits(1):
        out = joint_dual_certificate(p, R_bad, res.translation, max_iterations=300)
    upper = p.cost(R_bad, res.translation)
    assert not out.converged
    assert relative_gap(upper, out.lower_bound) > 1e-3
    assert out.lower_bound <= full_optimum(p) + 1e-6 * (1 + p.n)


def test_bad_start_option() -> None:
    rng = np.random.default_rng(5)
    p = _random_problem(rng, 4, 0, varied=False)
    with pytest.raises(ValueError, match="start"):
        joint_dual_certificate(p, np.eye(3), np.zeros(3), start="nope")


def test_non_rotation_candidate_is_rejected() -> None:
    rng = np.random.default_rng(6)
    p = _random_problem(rng, 4, 0, varied=False)
    with pytest.raises(ValueError, match="rotation"):
        joint_dual_certificate(p, 1.1 * np.eye(3), np.zeros(3))
