"""Ground-truth recovery, degeneracy reporting and the pruning building blocks."""

from __future__ import annotations

import itertools

import networkx as nx
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import certpose
from solvers import GNCParams, SolverStatus, WeightedTLSProblem, solve_gnc, solve_pruned
from solvers.lie import rotation_error_deg
from solvers.registration.pruning import (
    consistency_graph,
    max_clique,
    maximum_cliques,
    scalar_tls,
    vote_translation,
)
from tests.conftest import make_instance


def _ok(res, R, t):
    return rotation_error_deg(res.rotation, R) < 5 and np.linalg.norm(res.translation - t) < 0.05


@pytest.mark.parametrize("ratio", [0.0, 0.3, 0.6])
def test_gnc_alone_recovers_pose(rng, ratio):
    for _ in range(5):
        a, b, R, t, inl = make_instance(rng, 100, ratio)
        res = solve_gnc(WeightedTLSProblem(a, b, noise_bound=0.0554))
        assert res.success, res.message
        assert _ok(res, R, t)
        assert res.status is SolverStatus.CONVERGED
        # Every true inlier is within the bound (noise 0.01 << 0.0554).
        assert np.all(res.inliers[inl])


@pytest.mark.parametrize(("n", "ratio"), [(100, 0.0), (100, 0.9), (100, 0.95), (1000, 0.99)])
def test_register_recovers_pose_with_extreme_outliers(rng, n, ratio):
    for _ in range(3):
        a, b, R, t, inl = make_instance(rng, n, ratio)
        res = certpose.register(a, b, noise_bound=0.0554)
        assert res.success, res.message
        assert _ok(res, R, t)
        assert res.T_target_source.shape == (4, 4)
        np.testing.assert_allclose(res.T_target_source[:3, :3], res.rotation)
        assert res.info["max_clique_size"] >= inl.sum()
        assert res.cost == pytest.approx(
            WeightedTLSProblem(a, b, noise_bound=0.0554).cost(res.rotation, res.translation)
        )


def test_weights_select_among_conflicting_hypotheses(rng):
    # Two equally sized consistent sets; the weights decide which pose wins.
    a, b1, R1, t1, _ = make_instance(rng, 20, 0.0)
    a2, b2, R2, t2, _ = make_instance(rng, 20, 0.0)
    src, dst = np.vstack([a, a2]), np.vstack([b1, b2])
    w = np.r_[np.full(20, 1.0), np.full(20, 3.0)]
    res = certpose.register(src, dst, noise_bound=0.0554, weights=w)
    assert _ok(res, R2, t2)
    res = certpose.register(src, dst, noise_bound=0.0554, weights=w[::-1].copy(), prune="never")
    assert _ok(res, R1, t1)


def test_collinear_inliers_are_reported_degenerate(rng):
    s = np.linspace(-1, 1, 30)[:, None]
    a = s * np.array([1.0, 2.0, 0.5])
    b = a + np.array([0.1, 0.2, 0.3])
    res = certpose.register(a, b, noise_bound=0.01)
    assert not res.success
    assert res.status is SolverStatus.DEGENERATE
    assert "collinear" in res.message


def test_coincident_points_are_reported(rng):
    a = np.tile([1.0, 2.0, 3.0], (10, 1))
    res = certpose.register(a, a + 1.0, noise_bound=0.01)
    assert res.status is SolverStatus.DEGENERATE
    assert "coincident" in res.message


def test_zero_weights_leave_too_few_correspondences(rng):
    a, b, *_ = make_instance(rng, 10, 0.0)
    res = certpose.register(a, b, noise_bound=0.05, weights=np.r_[1.0, 1.0, np.zeros(8)])
    assert not res.success
    assert res.status is SolverStatus.INSUFFICIENT_INLIERS


def test_iteration_limit_is_reported(rng):
    a, b, *_ = make_instance(rng, 100, 0.5)
    res = solve_gnc(WeightedTLSProblem(a, b, noise_bound=0.0554), params=GNCParams(max_iterations=2))
    assert res.status is SolverStatus.MAX_ITERATIONS
    assert not res.success
    assert "iteration limit" in res.message


def test_bad_parameters():
    with pytest.raises(ValueError, match="mu_factor"):
        GNCParams(mu_factor=1.0)
    with pytest.raises(ValueError, match="`solver`"):
        certpose.register(np.eye(3), np.eye(3), noise_bound=0.1, solver="nope")  # type: ignore
    # A misspelt scope was accepted whenever no certificate was asked for.
    for certify in (False, True):
        with pytest.raises(ValueError, match="`scope` must be"):
            certpose.register(np.eye(3), np.eye(3), noise_bound=0.1, certify=certify,
                              scope="rotaton")  # type: ignore


def test_register_accepts_open3d_point_clouds(rng):
    import open3d as o3d

    a, b, R, t, _ = make_instance(rng, 50, 0.2)
    pa = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(a))
    pb = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(b))
    assert _ok(certpose.register(pa, pb, noise_bound=0.0554), R, t)


def test_consistency_graph_matches_definition(rng):
    a, b, *_ = make_instance(rng, 25, 0.5)
    beta = rng.uniform(0.03, 0.08, 25)
    adj = consistency_graph(a, b, beta)
    for i, j in itertools.combinations(range(25), 2):
        d = abs(np.linalg.norm(a[i] - a[j]) - np.linalg.norm(b[i] - b[j]))
        assert adj[i, j] == adj[j, i] == (d <= beta[i] + beta[j])
    assert np.all(np.diag(adj) == 0)


@pytest.mark.parametrize("density", [0.1, 0.3, 0.6, 0.9])
def test_max_clique_is_maximum_on_random_graphs(density):
    rng = np.random.default_rng(int(density * 100))
    for _ in range(10):
        n = int(rng.integers(5, 40))
        upper = np.triu(rng.uniform(size=(n, n)) < density, 1)
        adj = (upper | upper.T).astype(np.uint8)
        clique, exact = max_clique(adj, exact_max_vertices=None)
        assert exact
        sub = adj[np.ix_(clique, clique)]
        assert sub.sum() == len(clique) * (len(clique) - 1)  # it is a clique
        g = nx.from_numpy_array(adj)
        assert len(clique) == max(len(c) for c in nx.find_cliques(g))


def test_scalar_tls_is_exact_against_a_fine_grid(rng):
    for _ in range(100):
        n = int(rng.integers(1, 10))
        v, beta, w = rng.normal(size=n), rng.uniform(0.05, 0.5, n), rng.uniform(0, 2, n)
        x, c = scalar_tls(v, beta, w)
        xs = np.linspace(-6, 6, 120_001)
        grid = (w * np.minimum((xs[:, None] - v) ** 2 / beta**2, 1.0)).sum(axis=1)
        assert c <= grid.min() + 1e-9
        assert c == pytest.approx((w * np.minimum((x - v) ** 2 / beta**2, 1.0)).sum(), abs=1e-9)


def test_scalar_tls_is_exact_when_interval_ends_tie(rng):
    # Values on a grid with half-width noise bounds: every interval ends where the next one
    # starts, so the sweep meets ties (sorted in any order) at every endpoint.
    xs = np.linspace(-8, 8, 160_001)
    for _ in range(50):
        n = int(rng.integers(2, 12))
        v = rng.integers(-4, 5, n).astype(float)
        beta = np.full(n, 0.5)
        w = rng.choice([0.5, 1.0, 2.0], n)
        x, c = scalar_tls(v, beta, w)
        grid = (w * np.minimum((xs[:, None] - v) ** 2 / beta**2, 1.0)).sum(axis=1)
        assert c <= grid.min() + 1e-9
        assert c == pytest.approx((w * np.minimum((x - v) ** 2 / beta**2, 1.0)).sum(), abs=1e-9)


def test_vote_translation_recovers_the_translation_through_outliers(rng):
    a, b, R, t, inl = make_instance(rng, 60, 0.5)
    p = WeightedTLSProblem(a, b, noise_bound=0.0554)
    t_vote = vote_translation(p, R)
    assert np.linalg.norm(t_vote - t) < 0.02
    # Restricted to the outliers, the vote no longer finds it.
    assert np.linalg.norm(vote_translation(p, R, np.flatnonzero(~inl)) - t) > 0.1


def test_max_clique_flags_a_greedy_answer_on_large_dense_graphs():
    rng = np.random.default_rng(7)
    n = 300
    upper = np.triu(rng.uniform(size=(n, n)) < 0.5, 1)
    adj = (upper | upper.T).astype(np.uint8)
    clique, exact = max_clique(adj, exact_max_vertices=100)
    assert not exact
    assert adj[np.ix_(clique, clique)].sum() == len(clique) * (len(clique) - 1)
    # A planted clique is found, and proven maximum, through the core pruning.
    planted = rng.choice(n, 40, replace=False)
    adj[np.ix_(planted, planted)] = 1
    adj[planted, planted] = 0
    clique, exact = max_clique(adj, exact_max_vertices=100)
    assert len(clique) >= 40


def test_maximum_cliques_returns_every_tied_clique():
    adj = np.zeros((12, 12), dtype=np.uint8)
    for block in (range(0, 5), range(6, 11)):
        for i in block:
            for j in block:
                adj[i, j] = i != j
    adj[5, 0] = adj[0, 5] = 1  # a pendant edge does not make a bigger clique
    cliques, exact = maximum_cliques(adj)
    assert exact
    assert sorted(map(tuple, cliques)) == [(0, 1, 2, 3, 4), (6, 7, 8, 9, 10)]


def test_a_tied_mirror_image_clique_does_not_win(rng):
    # Five true inliers and five outliers forming a mirror image of another shape: pairwise
    # distances agree (a tied maximum clique) but no proper rotation aligns them.
    a_in = rng.uniform(-0.5, 0.5, (5, 3))
    R, t = Rotation.random(random_state=rng).as_matrix(), np.array([0.2, -0.1, 0.3])
    b_in = a_in @ R.T + t
    a_mir = rng.uniform(-0.5, 0.5, (5, 3)) + 3.0
    b_mir = (a_mir * np.array([1.0, 1.0, -1.0])) @ Rotation.random(random_state=rng).as_matrix().T + 10.0
    a_noise, b_noise = rng.uniform(-0.5, 0.5, (20, 3)), rng.uniform(-5, 5, (20, 3))
    src = np.vstack([a_mir, a_in, a_noise])  # the mirror set first: no luck from ordering
    dst = np.vstack([b_mir, b_in, b_noise])
    res = solve_pruned(WeightedTLSProblem(src, dst, noise_bound=0.01))
    assert res.info["tied_max_cliques"] >= 2
    assert _ok(res, R, t)
    assert np.all(res.inliers[5:10])


def test_peel_to_core_matches_networkx() -> None:
    """The compiled k-core peeling of the pruning step against networkx's k_core."""
    import networkx as nx

    from solvers.registration.pruning import _peel_to_core

    rng = np.random.default_rng(0)
    for _ in range(200):
        n = int(rng.integers(1, 60))
        A = np.triu((rng.random((n, n)) < rng.uniform(0, 0.5)).astype(np.uint8), 1)
        A = A + A.T
        k = int(rng.integers(1, 10))
        got = set(_peel_to_core(A, A.sum(axis=1), k).tolist())
        assert got == set(nx.k_core(nx.from_numpy_array(A), k).nodes())


def test_register_time_limit_covers_the_solve(monkeypatch) -> None:
    """``time_limit`` is the call's budget: the certifier gets what the solver left."""
    import solvers.certify as sc
    from certpose import register

    seen = []
    real = sc.certify_result

    def spy(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        seen.append(kwargs["time_limit"])
        return real(*args, **kwargs)

    monkeypatch.setattr(sc, "certify_result", spy)
    rng = np.random.default_rng(3)
    src = rng.uniform(-1, 1, (40, 3))
    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    res = register(src, src @ R.T + [0.1, 0.2, 0.3], noise_bound=0.05, certify=True, time_limit=5.0)
    assert res.certificate is not None and res.certificate.certified
    assert len(seen) == 1 and 0 < seen[0] < 5.0
