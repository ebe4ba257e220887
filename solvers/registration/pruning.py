"""Outlier pruning for extreme outlier rates (TEASER++-style).

Pairwise consistency of translation-invariant measurements gives a graph whose maximum clique
holds the mutually consistent correspondences; translation is then voted exactly per component.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.jit import compiled
from solvers.problem import WeightedTLSProblem

__all__ = [
    "consistency_graph",
    "consistency_edge_list",
    "max_clique",
    "maximum_cliques",
    "scalar_tls",
    "vote_translation",
    "prune_max_clique",
    "prune_maximum_cliques",
]

log = logging.getLogger(__name__)


# Slack that covers the rounding of the lengths (a few ulps each): with it, no pair of true
# inliers is ever left out, which the certifier's soundness needs (a supergraph is still sound).
ROUNDING_REL_SLACK = 1e-9
ROUNDING_ABS_SLACK = 8 * float(np.finfo(np.float64).eps)


def _kernel_inputs(source: ArrayLike, target: ArrayLike, noise_bound: ArrayLike):
    _kernels = compiled("solvers.registration._kernels")  # numba: imported on first solve

    at = np.ascontiguousarray(np.asarray(source, dtype=np.float64).T)
    bt = np.ascontiguousarray(np.asarray(target, dtype=np.float64).T)
    beta = np.asarray(noise_bound, dtype=np.float64)
    if beta.ndim == 0:
        beta = np.full(at.shape[1], float(beta))
    arr = _kernels.as_kernel_array
    return _kernels, arr(at), arr(bt), arr(beta)


def consistency_graph(
    source: ArrayLike, target: ArrayLike, noise_bound: ArrayLike, cbar: float = 1.0,
    *, rounding_slack: bool = False,
) -> NDArray[np.uint8]:
    """Dense adjacency matrix of the pairwise-consistency graph, shape (N, N), uint8.

    Correspondences ``i`` and ``j`` are consistent when the lengths of the translation-invariant
    measurements ``a_j - a_i`` and ``b_j - b_i`` differ by at most ``cbar (beta_i + beta_j)``,
    which holds for every pair of inliers. With ``rounding_slack`` the bound is widened by
    ``1e-9`` relative and ``8 eps`` times the lengths, so that rounding never drops such a pair
    (what a certificate needs).
    """
    k, at, bt, beta = _kernel_inputs(source, target, noise_bound)
    rel, eps = (ROUNDING_REL_SLACK, ROUNDING_ABS_SLACK) if rounding_slack else (0.0, 0.0)
    return k.consistency_matrix(at, bt, beta, float(cbar), rel, eps)


def consistency_edge_list(
    source: ArrayLike, target: ArrayLike, noise_bound: ArrayLike, cbar: float = 1.0,
    *, rounding_slack: bool = False,
) -> NDArray[np.int64]:
    """The edges ``(i, j)``, ``i < j``, shape (E, 2), of :func:`consistency_graph`, without
    building the N^2-byte matrix."""
    k, at, bt, beta = _kernel_inputs(source, target, noise_bound)
    rel, eps = (ROUNDING_REL_SLACK, ROUNDING_ABS_SLACK) if rounding_slack else (0.0, 0.0)
    return k.consistency_edge_list(at, bt, beta, float(cbar), rel, eps)


def _peel_to_core(adj: NDArray[np.uint8], deg: NDArray[np.int64], k: int) -> NDArray[np.int64]:
    """Vertices of the ``k``-core: drop every vertex of degree < ``k`` until none is left
    (compiled: numpy's rounds cost 30-60 us at N = 100, a tenth of a whole solve)."""
    _kernels = compiled("solvers.registration._kernels")

    return _kernels.k_core(adj, np.ascontiguousarray(deg, dtype=np.int64), int(k))


GREEDY_STARTS = 16
"""Greedy cliques grown for the lower bound that peels the graph before the exact search."""
WORK_BUDGET = 10_000_000
"""Default budget of the exact maximum-clique search, in adjacency look-ups (tens of ms)."""
BITSET_MIN_VERTICES = 256
"""Cores larger than this go to the bitset search (:mod:`._clique_kernels`); smaller ones to
the MCQ kernel, already compiled for the small problems (a first small solve never compiles the
bitset search) and as fast on small cores (the 181-vertex core of the 3DMatch pair: about 3 ms
both, where the bitset search's greedy start costs most of its time)."""
BITSET_WORDS_PER_LOOKUP = 8
"""The bitset search's budget in 64-bit word operations per adjacency look-up of
``max_work`` (a word operation costs about an eighth of a look-up in the MCQ kernel)."""


def maximum_cliques(
    adjacency: ArrayLike,
    *,
    limit: int = 16,
    exact_max_vertices: int | None = None,
    max_work: int | None = WORK_BUDGET,
) -> tuple[list[NDArray[np.int64]], bool]:
    """Maximum cliques of an undirected graph: one proven maximum, and up to ``limit`` tied.

    Greedy cliques (from the highest-degree vertices) give a lower bound ``L``; every clique of
    size ``>= L`` lies in the ``(L-1)``-core, which for registration graphs is usually small or
    already complete. What is left goes to a branch and bound with greedy-colouring bounds
    (Tomita's MCQ, compiled): first one clique larger than ``L`` or the proof that none
    exists, then the cliques tied with it (a second, bounded search). Dense consistency graphs
    of real features hold many tied maximum cliques (54 of 74 vertices on the 3DMatch pair):
    listing all maximal cliques, as igraph does, took 0.6 s there; this takes milliseconds.
    Ties matter with few inliers: another clique of the same size can hold outliers.

    Cores of more than :data:`BITSET_MIN_VERTICES` vertices go instead to a bitset search
    (San Segundo's BBMC with re-colouring and an infra-chromatic bound, started from greedy
    cliques grown from 256 vertices, ties listed in the same search; compiled on first use):
    on dense graphs whose core is the whole graph (N = 1000, 98% outliers placed among the
    inliers, clique number 23-30) it proved the maximum and listed the ties of 15 such graphs
    in 16-49 ms each (median; load average 12 on 2 cores), where the MCQ search ran out of
    its 10 M budget on 12 of them after 87-119 ms (unbounded, it took 100-650 ms).

    Parameters
    ----------
    adjacency : (N, N) array_like
        Symmetric 0/1 adjacency matrix with a zero diagonal.
    limit : int
        At most this many tied maximum cliques are returned.
    exact_max_vertices : int or None
        Largest reduced graph handed to the exact search; ``None`` always searches exactly.
    max_work : int or None
        Budget of the exact search in adjacency look-ups (about 5 ns each; ``None``: unbounded,
        exponential time in the worst case). When it runs out, the largest clique found is
        returned, flagged as inexact; the tie search gets a quarter of it and returns the ties
        found so far. The bitset search counts :data:`BITSET_WORDS_PER_LOOKUP` 64-bit word
        operations per look-up, its tie listing included.

    Returns
    -------
    cliques : list of (m,) ndarray of int64
        Sorted vertex indices of each clique, all of the same size (one vertex when there are
        no edges); the first is the one the search proved maximum.
    exact : bool
        True when the cliques are proven maximum.
    """
    _kernels = compiled("solvers.registration._kernels")

    adj = _kernels.as_kernel_array(adjacency, np.uint8)
    if adj.shape[0] == 0:
        return [np.empty(0, dtype=np.int64)], True
    return _max_cliques_from(adj, _kernels.row_degrees(adj), limit, exact_max_vertices, max_work)


_NO_BUDGET = int(np.iinfo(np.int64).max)


def _max_cliques_from(
    adj: NDArray[np.uint8],
    deg: NDArray[np.int64],
    limit: int,
    exact_max_vertices: int | None,
    max_work: int | None,
) -> tuple[list[NDArray[np.int64]], bool]:
    """:func:`maximum_cliques` of a kernel-ready, non-empty ``adj`` with vertex degrees ``deg``."""
    _kernels = compiled("solvers.registration._kernels")
    n = adj.shape[0]
    budget = _NO_BUDGET if max_work is None else int(max_work)
    order = np.argsort(-deg, kind="stable")
    best = np.sort(_kernels.multistart_greedy_clique(adj, deg, order, GREEDY_STARTS))
    core = _peel_to_core(adj, deg, best.size - 1)
    if core.size <= best.size:
        return [best], True
    if core.size == n:
        sub, sub_deg = adj, deg  # nothing peeled (dense graphs): no copy
    else:
        sub = np.ascontiguousarray(adj[np.ix_(core, core)])
        sub_deg = _kernels.row_degrees(sub)
    if int(sub_deg.sum()) == core.size * (core.size - 1):
        return [core], True  # the core is itself a clique
    if exact_max_vertices is not None and core.size > exact_max_vertices:
        log.info("max clique: %d-vertex core left after pruning exceeds %d; keeping the greedy "
                 "clique of %d (not proven maximum)", core.size, exact_max_vertices, best.size)
        return [best], False
    sub_order = np.argsort(-sub_deg, kind="stable")
    if core.size > BITSET_MIN_VERTICES:
        return _bitset_search(sub, sub_order, core, best, limit, budget)
    found, count, size, exact, _ = _kernels.max_clique_bnb(sub, sub_order, best.size, 0, 1, budget)
    if count:
        best = np.sort(core[found[0]])
    if not exact:
        log.info("max clique: search stopped after %d look-ups; keeping a clique of %d (not "
                 "proven maximum)", budget, best.size)
        return [best], False
    if limit <= 1:
        return [best], True
    ties, count, _, _, _ = _kernels.max_clique_bnb(sub, sub_order, 0, best.size, limit,
                                                   max(budget // 4, 1))
    cliques = [best]
    seen = {best.tobytes()}
    for row in ties[:count]:
        c = np.sort(core[row])
        if c.tobytes() not in seen and len(cliques) < limit:
            seen.add(c.tobytes())
            cliques.append(c)
    return cliques, True


def _bitset_search(sub, sub_order, core, best, limit, budget):
    """:func:`maximum_cliques` on a large core: the bitset search (compiled on first use)."""
    _clique_kernels = compiled("solvers.registration._clique_kernels")
    seed = np.searchsorted(core, best).astype(np.int64)  # the greedy clique (within the core)
    words = min(budget, np.iinfo(np.int64).max // BITSET_WORDS_PER_LOOKUP)
    found, count, size, exact, _, work = _clique_kernels.max_clique_bitset(
        sub, np.ascontiguousarray(sub_order, dtype=np.int64), seed, max(int(limit), 1),
        words * BITSET_WORDS_PER_LOOKUP)
    cliques = [np.sort(core[row]) for row in found[:count]]
    if not exact:
        log.info("max clique: search stopped after %d word operations; keeping a clique of %d "
                 "(not proven maximum)", work, size)
    return cliques, bool(exact)


def max_clique(
    adjacency: ArrayLike,
    *,
    exact_max_vertices: int | None = None,
    max_work: int | None = WORK_BUDGET,
) -> tuple[NDArray[np.int64], bool]:
    """One maximum clique (see :func:`maximum_cliques`) and whether it is proven maximum."""
    cliques, exact = maximum_cliques(adjacency, limit=1, exact_max_vertices=exact_max_vertices,
                                     max_work=max_work)
    return cliques[0], exact


def scalar_tls(
    values: ArrayLike, noise_bound: ArrayLike, weights: ArrayLike | None = None, cbar2: float = 1.0
) -> tuple[float, float]:
    """Exact minimiser of ``sum_k w_k min((x - v_k)^2 / beta_k^2, cbar2)`` over scalar ``x``.

    Adaptive voting: the cost is quadratic between consecutive interval endpoints
    ``v_k -/+ beta_k cbar``; sweeping the sorted endpoints with running sums evaluates every piece.

    Returns
    -------
    x : float
        The minimiser.
    cost : float
        Its cost.
    """
    _kernels = compiled("solvers.registration._kernels")

    v = np.ascontiguousarray(values, dtype=np.float64).ravel()
    n = v.size
    if n == 0:
        raise ValueError("`values` must not be empty.")
    beta = np.asarray(noise_bound, dtype=np.float64)
    beta = np.full(n, float(beta)) if beta.ndim == 0 else np.ascontiguousarray(beta)
    w = np.ones(n) if weights is None else np.ascontiguousarray(weights, dtype=np.float64)
    cbar = float(np.sqrt(cbar2))
    ends = np.concatenate([v - beta * cbar, v + beta * cbar])
    order = np.argsort(ends)  # any order of ties: the cost is continuous at every endpoint
    x, cost, found = _kernels.scalar_tls(
        _kernels.as_kernel_array(v), _kernels.as_kernel_array(beta), _kernels.as_kernel_array(w),
        float(cbar2), ends, order,
    )
    if not found:
        # No piece beats "everything is an outlier": every x is optimal; report the median.
        return float(np.median(v)), float(cost)
    return float(x), float(cost)


def vote_translation(
    problem: WeightedTLSProblem, rotation: ArrayLike, indices: ArrayLike | None = None
) -> NDArray[np.float64]:
    """Exact TLS translation given the rotation, one axis at a time (TEASER++'s adaptive voting).

    Each component of ``t`` minimises :func:`scalar_tls` over the residuals
    ``b_k - R a_k`` of the correspondences ``indices`` (default all), with their noise bounds
    and weights. The result is exact per axis, not jointly; callers compare it with their own
    translation on the full cost.
    """
    _kernels = compiled("solvers.registration._kernels")

    R = np.asarray(rotation, dtype=np.float64)
    if indices is None:
        resid = problem.target - problem.source @ R.T
        beta, w = problem.noise_bound, problem.weights
    else:
        idx = np.asarray(indices)
        resid = problem.target[idx] - problem.source[idx] @ R.T
        beta, w = problem.noise_bound[idx], problem.weights[idx]
    if resid.shape[0] == 0:
        raise ValueError("`indices` must not be empty.")
    arr = _kernels.as_kernel_array
    beta = arr(beta)
    return _vote_rows(np.ascontiguousarray(resid.T), beta, arr(w), float(problem.cbar2),
                      uniform=bool((beta == beta[0]).all()))


def _vote_rows(
    vals: NDArray[np.float64], beta: NDArray[np.float64], w: NDArray[np.float64], cbar2: float,
    *, uniform: bool,
) -> NDArray[np.float64]:
    """:func:`vote_translation` on the residuals ``vals`` (3, n), C-contiguous and writable, with
    kernel-ready ``beta`` and ``w`` (n,), ``uniform`` when every ``beta`` is the same: one scalar
    TLS per row, their setup shared (this runs once per pruned solve: small-N overhead)."""
    _kernels = compiled("solvers.registration._kernels")
    # Ties in any order (see scalar_tls): quicksort is faster.
    if uniform:  # every interval's ends in the order of the values
        order_lo = order_hi = np.argsort(vals, axis=1)
    else:
        half = beta if cbar2 == 1.0 else beta * math.sqrt(cbar2)
        order_lo = np.argsort(vals - half, axis=1)
        order_hi = np.argsort(vals + half, axis=1)
    t, found = _kernels.scalar_tls_rows(vals, beta, w, cbar2, order_lo, order_hi)
    if not found.all():
        for d in np.flatnonzero(~found):
            t[d] = np.median(vals[d])  # no piece beats all-outliers: any x is optimal
    return t


def prune_max_clique(
    source: NDArray[np.float64],
    target: NDArray[np.float64],
    noise_bound: NDArray[np.float64],
    cbar2: float = 1.0,
    *,
    exact_max_vertices: int | None = None,
    max_work: int | None = WORK_BUDGET,
) -> tuple[NDArray[np.int64], int, bool]:
    """Indices of one maximum consistent set, the number of graph edges, and exactness."""
    cliques, n_edges, exact = prune_maximum_cliques(
        source, target, noise_bound, cbar2, limit=1, exact_max_vertices=exact_max_vertices,
        max_work=max_work,
    )
    return cliques[0], n_edges, exact


def prune_maximum_cliques(
    source: NDArray[np.float64],
    target: NDArray[np.float64],
    noise_bound: NDArray[np.float64],
    cbar2: float = 1.0,
    *,
    limit: int = 16,
    exact_max_vertices: int | None = None,
    max_work: int | None = WORK_BUDGET,
) -> tuple[list[NDArray[np.int64]], int, bool]:
    """Tied maximum consistent sets (up to ``limit``), the number of edges, and exactness."""
    _, at, bt, beta = _kernel_inputs(source, target, noise_bound)
    return _prune_rows(at, bt, beta, cbar2, limit=limit, exact_max_vertices=exact_max_vertices,
                       max_work=max_work)


def _prune_rows(
    at: NDArray[np.float64],
    bt: NDArray[np.float64],
    beta: NDArray[np.float64],
    cbar2: float,
    *,
    limit: int,
    exact_max_vertices: int | None,
    max_work: int | None,
) -> tuple[list[NDArray[np.int64]], int, bool]:
    """:func:`prune_maximum_cliques` on kernel-ready points ``at``, ``bt`` (3, N) and ``beta``."""
    if at.shape[1] == 0:
        return [np.empty(0, dtype=np.int64)], 0, True
    _kernels = compiled("solvers.registration._kernels")
    adj = _kernels.consistency_matrix(at, bt, beta, math.sqrt(cbar2), 0.0, 0.0)
    deg = _kernels.row_degrees(adj)
    cliques, exact = _max_cliques_from(adj, deg, limit, exact_max_vertices, max_work)
    n_edges = int(deg.sum()) // 2
    log.debug("consistency graph: %d vertices, %d edges, %d maximum clique(s) of %d (exact: %s)",
              at.shape[1], n_edges, len(cliques), cliques[0].size, exact)
    return cliques, n_edges, exact
