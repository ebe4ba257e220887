"""Clique decomposition and the exact clique branch and bound (solvers.certify.cliques)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from solvers import solve_registration
from solvers.certify._kernels import _horn_lambda_max
from solvers.certify.cliques import candidate_cliques, clique_optimum
from solvers.problem import WeightedTLSProblem
from tests.conftest import make_instance
from tests.test_certify_audit import FAMILIES, exact_optimum, make_family


@settings(max_examples=1500, deadline=None)
@given(arrays(np.float64, (3, 3), elements=st.floats(-1e3, 1e3)),
       st.floats(1e-6, 1e6))
def test_horn_root_is_a_tight_upper_bound(H: np.ndarray, scale: float) -> None:
    """QCP Newton from above: never below the SVD max trace, and within 1e-5 of it."""
    H = H * scale
    assume(not np.any((np.abs(H) > 0) & (np.abs(H) < 1e-100)))  # callers scale to unit size
    U, s, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt)) or 1.0
    true = s[0] + s[1] + d * s[2]
    lam = _horn_lambda_max(H, np.sqrt(3.0) * np.linalg.norm(H) * (1 + 1e-9) + 1e-300)
    norm = np.linalg.norm(H)
    assert lam >= true - 1e-12 * norm
    assert lam <= true + 1e-5 * norm + 1e-299


def test_horn_root_near_identity() -> None:
    """Nearly rank-deficient and identity-like covariances (the near-identity case)."""
    for H in (np.eye(3), np.diag([1.0, 1.0, 1e-12]), np.diag([1.0, 1e-9, -1e-9]), np.zeros((3, 3))):
        U, s, Vt = np.linalg.svd(H)
        d = np.sign(np.linalg.det(U @ Vt)) or 1.0
        true = s[0] + s[1] + d * s[2]
        lam = _horn_lambda_max(H, np.sqrt(3.0) * np.linalg.norm(H) * (1 + 1e-9) + 1e-300)
        assert true - 1e-12 <= lam <= true + 1e-5


@pytest.mark.parametrize("family", ["uniform", "uneven", "beta", "cbar2", "symmetric",
                                    "collinear", "all_outliers", "scaled_large"])
def test_branch_and_bound_finds_the_exact_optimum(family: str) -> None:
    """K = 13-15 (past the batched enumeration): value and lower bound match enumeration."""
    rng = np.random.default_rng(FAMILIES.index(family))
    for _ in range(4):
        k = int(rng.integers(13, 16))
        p = make_family(rng, family, k)
        exact = exact_optimum(p)
        res = solve_registration(p)
        order = np.argsort(-p.residuals_sq(res.rotation, res.translation))
        for upper in (p.cbar2 * p.weights.sum() * 1.01 + 1.0, res.cost):
            out = clique_optimum(p, upper, order)
            assert out.complete
            assert out.lower_bound <= exact
            assert out.lower_bound >= exact - 1e-6 * (1 + exact)
            if np.isfinite(out.best_cost):  # a leaf beat `upper`
                assert out.best_cost == pytest.approx(exact, rel=1e-8, abs=1e-10)
                assert p.cost(out.rotation, out.translation) <= out.best_cost * (1 + 1e-9) + 1e-12


def test_node_budget_gives_a_weak_but_valid_bound() -> None:
    rng = np.random.default_rng(0)
    src, dst, *_ = make_instance(rng, 60, 0.0)
    p = WeightedTLSProblem(src, dst, noise_bound=0.0554)
    out = clique_optimum(p, p.weights.sum(), max_nodes=10)
    assert not out.complete and out.lower_bound == 0.0


def test_the_optimum_inlier_set_lies_in_a_candidate_clique() -> None:
    rng = np.random.default_rng(3)
    for ratio in (0.5, 0.9):
        src, dst, R, t, inl = make_instance(rng, 80, ratio)
        p = WeightedTLSProblem(src, dst, noise_bound=0.0554)
        res = solve_registration(p)
        cliques, complete = candidate_cliques(p, res.cost, limit=100)
        assert complete and cliques
        S = set(np.flatnonzero(p.residuals_sq(res.rotation, res.translation) < p.cbar2))
        assert any(S <= set(c) for c in cliques)
        # Every returned clique is a clique and could beat the pose.
        for c in cliques:
            assert p.cbar2 * (p.weights.sum() - p.weights[c].sum()) < res.cost * (1 + 1e-9)
