"""Clique decomposition and the exact clique branch and bound (solvers.certify.cliques)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from solvers import solve_registration
from solvers.certify._kernels import _horn_lambda_max, heavy_maximal_cliques
from solvers.certify.cliques import (
    candidate_cliques,
    clique_number_bound,
    clique_optimum,
    consistency_edges,
)
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


def test_clique_listing_matches_networkx_and_stops_at_its_limits() -> None:
    """The compiled Bron-Kerbosch lists exactly networkx's maximal cliques that are large and
    heavy enough, on random graphs and weights; it stops at `limit` and at the node budget."""
    import networkx as nx

    rng = np.random.default_rng(1)
    for it in range(300):
        n = int(rng.integers(1, 30))
        upper = np.triu(rng.uniform(size=(n, n)) < rng.uniform(0.1, 0.9), 1)
        adj = (upper | upper.T).astype(np.uint8)
        w = rng.uniform(0.1, 2.0, n) if it % 2 else np.ones(n)
        s_min, thr = int(rng.integers(1, 6)), float(rng.uniform(0, 0.5 * w.sum()))
        flat, off, count, complete, _ = heavy_maximal_cliques(adj, w, s_min, thr, 10**6, 10**8)
        got = sorted(tuple(sorted(flat[off[k]:off[k + 1]].tolist())) for k in range(count))
        want = sorted(tuple(sorted(c)) for c in nx.find_cliques(nx.from_numpy_array(adj))
                      if len(c) >= s_min and w[c].sum() > thr)
        assert complete and got == want
    upper = np.triu(rng.uniform(size=(40, 40)) < 0.5, 1)
    adj = (upper | upper.T).astype(np.uint8)
    _, _, count, complete, _ = heavy_maximal_cliques(adj, np.ones(40), 1, 0.0, 5, 10**8)
    assert not complete and count == 6  # stopped at the sixth clique
    _, _, _, complete, nodes = heavy_maximal_cliques(adj, np.ones(40), 1, 0.0, 10**6, 20)
    assert not complete and nodes == 21


@pytest.mark.parametrize("family", ["uniform", "uneven", "beta", "all_outliers", "cbar2"])
def test_clique_number_bound_is_sound_and_is_the_clique_number(family: str) -> None:
    import networkx as nx

    rng = np.random.default_rng(5)
    for _ in range(5):
        p = make_family(rng, family, 9)
        opt = exact_optimum(p)
        lower = clique_number_bound(p, float(p.cbar2 * p.weights.sum()) + 1.0)
        assert lower <= opt * (1 + 1e-9) + 1e-12
        # With an upper bound no clique can miss, it is cbar2 (W - the omega heaviest).
        act = np.flatnonzero(p.weights > 0)
        g = nx.Graph()
        g.add_nodes_from(range(act.size))
        g.add_edges_from(consistency_edges(p, act).tolist())
        omega = max(len(c) for c in nx.find_cliques(g)) if act.size else 0
        top = np.sort(p.weights[act])[::-1][:omega].sum()
        assert lower == pytest.approx(max(p.cbar2 * (p.weights.sum() - top), 0.0),
                                      rel=1e-9, abs=1e-9)
        # Never above the cost it is given.
        assert clique_number_bound(p, 0.5 * opt) <= 0.5 * opt


@pytest.mark.parametrize("family", ["uniform", "uneven", "beta", "all_outliers", "cbar2"])
def test_the_clique_number_best_gap_is_never_above_the_bound_s_gap(family: str) -> None:
    """``skip_futile``'s test is sound: the clique-number bound's gap is never below the gap
    ``_clique_number_best_gap`` says it could reach (else a skip could lose a certificate)."""
    from solvers.certificate import undiluted_gap
    from solvers.certify.front import _clique_number_best_gap, _normalised, _outlier_cost

    rng = np.random.default_rng(8)
    for _ in range(5):
        pn, _ = _normalised(make_family(rng, family, 9))
        res = solve_registration(pn, method="auto")
        R, t = res.rotation, res.translation
        u = pn.cost(R, t)
        gap = undiluted_gap(u, clique_number_bound(pn, u), _outlier_cost(pn, R, t))
        best, k = _clique_number_best_gap(pn, R, t)
        assert best <= gap + 1e-12
        assert k == int(np.count_nonzero((pn.residuals_sq(R, t) < pn.cbar2) & (pn.weights > 0)))


def test_skip_futile_still_searches_a_clique_number_that_could_certify() -> None:
    """Exact inliers and outliers 1.5 noise bounds off (consistent with every inlier): the
    listing gives up (time limit), the candidate's inliers would certify with a clique number
    of their count, so the clique number is searched with ``skip_futile`` as without it."""
    from scipy.spatial.transform import Rotation

    from solvers.certify import certify_result

    rng = np.random.default_rng(3)
    k, m, beta = 20, 40, 0.01
    src = rng.uniform(-0.5, 0.5, (k + m, 3))
    dst = src @ Rotation.random(random_state=rng).as_matrix().T + rng.normal(size=3)
    off = rng.normal(size=(m, 3))
    dst[k:] += 1.5 * beta * off / np.linalg.norm(off, axis=1, keepdims=True)
    p = WeightedTLSProblem(src, dst, noise_bound=beta)
    res = solve_registration(p, method="auto")
    assert p.inliers(res.rotation, res.translation).sum() == k
    plain = certify_result(p, res, time_limit=1e-6).certificate
    skip = certify_result(p, res, time_limit=1e-6, skip_futile=True).certificate
    assert plain.method == skip.method == "clique_number"
    assert skip.lower_bound == plain.lower_bound and skip.relative_gap == plain.relative_gap
    assert "not attempted" not in skip.message


def test_horn_root_at_a_triple_root_is_tight() -> None:
    """H = -19 I (a reflection's triple root): Newton alone stopped 4.7e-5 relative above."""
    off = np.full((3, 3), 1e-6)
    np.fill_diagonal(off, 0.0)
    for H in (-19.0 * np.eye(3) + off, -np.eye(3), -2.5 * np.eye(3)):
        U, s, Vt = np.linalg.svd(H)
        d = np.sign(np.linalg.det(U @ Vt)) or 1.0
        true = s[0] + s[1] + d * s[2]
        lam = _horn_lambda_max(H, np.sqrt(3.0) * np.linalg.norm(H) * (1 + 1e-9) + 1e-300)
        norm = np.linalg.norm(H)
        assert true - 1e-12 * norm <= lam <= true + 1e-7 * norm
