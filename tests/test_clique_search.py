"""The bitset maximum-clique search (``solvers.registration._clique_kernels``) against networkx.

Random graphs of every density, with and without planted cliques: every clique returned is a
clique of the same size; when the search says it is exact, that size is networkx's clique
number; when it lists fewer ties than asked for, it lists every maximum clique.
"""

from __future__ import annotations

import networkx as nx
import numpy as np
import pytest

from solvers import jit
from solvers.registration import pruning
from solvers.registration._clique_kernels import max_clique_bitset


def _random_graph(rng, n, density, planted=0):
    upper = np.triu(rng.random((n, n)) < density, 1)
    adj = (upper | upper.T).astype(np.uint8)
    if planted:
        members = rng.choice(n, planted, replace=False)
        adj[np.ix_(members, members)] = 1
        adj[members, members] = 0
    return adj


def _is_clique(adj, vertices):
    sub = adj[np.ix_(vertices, vertices)]
    return int(sub.sum()) == len(vertices) * (len(vertices) - 1)


def _search(adj, limit=16, max_work=10**12, seed=()):
    deg = adj.sum(axis=1)
    order = np.argsort(-deg, kind="stable").astype(np.int64)
    found, count, size, exact, _, _ = max_clique_bitset(
        adj, order, np.asarray(seed, dtype=np.int64), limit, max_work)
    return [np.sort(row) for row in found[:count]], size, exact


def _maximum_cliques_nx(adj):
    cliques = [tuple(sorted(c)) for c in nx.find_cliques(nx.from_numpy_array(adj))]
    omega = max(len(c) for c in cliques)
    return omega, {c for c in cliques if len(c) == omega}


def test_bitset_search_matches_networkx_on_random_graphs():
    rng = np.random.default_rng(12)
    for trial in range(400):
        # Sizes for which networkx lists every maximal clique quickly.
        density, n_max = [(0.02, 120), (0.1, 100), (0.3, 70), (0.5, 50), (0.7, 35), (0.9, 24),
                          (0.97, 20)][int(rng.integers(7))]
        n = int(rng.integers(1, n_max))
        planted = int(rng.integers(0, n // 3 + 1)) if trial % 3 == 0 else 0
        adj = _random_graph(rng, n, density, planted)
        omega, maximum = _maximum_cliques_nx(adj)
        limit = int(rng.choice([1, 2, 16]))
        cliques, size, exact = _search(adj, limit=limit)
        assert exact
        assert size == omega, (trial, n, density)
        assert 1 <= len(cliques) <= limit
        assert len({c.tobytes() for c in cliques}) == len(cliques)  # no clique twice
        for c in cliques:
            assert c.size == size and _is_clique(adj, c)
            assert tuple(c) in maximum
        if len(cliques) < limit:
            assert {tuple(c) for c in cliques} == maximum  # every tie listed


def test_bitset_search_on_dense_consistency_like_graphs():
    """Larger, denser graphs (clique number from networkx's branch and bound)."""
    rng = np.random.default_rng(5)
    for n, density, planted in [(150, 0.3, 0), (200, 0.3, 25), (200, 0.5, 0), (90, 0.8, 0),
                                (300, 0.1, 40)]:
        adj = _random_graph(rng, n, density, planted)
        omega = nx.max_weight_clique(nx.from_numpy_array(adj), weight=None)[1]
        cliques, size, exact = _search(adj)
        assert exact and size == omega
        assert all(c.size == omega and _is_clique(adj, c) for c in cliques)


def test_bitset_search_budget_keeps_a_valid_clique():
    rng = np.random.default_rng(3)
    adj = _random_graph(rng, 200, 0.5)
    cliques, size, exact = _search(adj, max_work=50_000)
    assert not exact
    assert size >= 2 and all(c.size == size and _is_clique(adj, c) for c in cliques)
    # A seed clique larger than the greedy ones is kept when the budget runs out at once.
    seed = np.arange(12)
    adj[np.ix_(seed, seed)] = 1
    adj[seed, seed] = 0
    cliques, size, exact = _search(adj, max_work=1, seed=seed)
    assert not exact and size >= 12 and _is_clique(adj, cliques[0])


@pytest.mark.parametrize("n", [0, 1, 2, 70])
def test_bitset_search_edgeless_graphs(n):
    adj = np.zeros((n, n), dtype=np.uint8)
    cliques, size, exact = _search(adj, limit=3)
    assert exact
    assert size == min(n, 1)
    assert len(cliques) == (min(n, 3) if n else 0)


def test_maximum_cliques_routes_large_cores_to_the_bitset_search(monkeypatch):
    """Through `maximum_cliques`: the same answers on both searches, and against networkx."""
    rng = np.random.default_rng(8)
    for _ in range(6):
        n = pruning.BITSET_MIN_VERTICES + int(rng.integers(1, 60))
        adj = _random_graph(rng, n, 0.25, planted=int(rng.integers(0, 20)))
        omega = nx.max_weight_clique(nx.from_numpy_array(adj), weight=None)[1]
        cliques, exact = pruning.maximum_cliques(adj, max_work=None)
        assert exact and cliques[0].size == omega
        assert all(c.size == omega and _is_clique(adj, c) for c in cliques)
        monkeypatch.setattr(pruning, "BITSET_MIN_VERTICES", 10**9)  # the MCQ search
        mcq, exact_mcq = pruning.maximum_cliques(adj, max_work=None)
        monkeypatch.undo()
        assert exact_mcq
        assert {c.tobytes() for c in cliques} == {c.tobytes() for c in mcq} or (
            len(cliques) == len(mcq) == 16)
    # One compilation: the callers pass exactly the declared signature.
    spec, = jit.declared(["solvers.registration._clique_kernels"])
    assert [tuple(s) for s in spec.dispatcher().signatures] == [spec.signature]
