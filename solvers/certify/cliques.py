"""Clique decomposition of weighted TLS, and exact optima of small clique subproblems.

Why it is sound
---------------
Let ``S(R, t) = {i : r_i^2 < cbar2}`` be a pose's strict inliers. Two of them satisfy
``| ||a_j - a_i|| - ||b_j - b_i|| | <= cbar (beta_i + beta_j)`` (triangle inequality), so ``S`` is
a clique of the pairwise-consistency graph and lies in some maximal clique ``C``. Every term
outside ``C`` is then an outlier and costs ``cbar2 w_i``, so

    ``f(R, t) = f_C(R, t) + cbar2 W(not C) >= f_C^* + cbar2 W(not C)``,

and ``min f >= min_C [lb(f_C^*) + cbar2 W(not C)]`` over the maximal cliques. Cliques with
``cbar2 W(not C) >= u`` cannot beat a pose of cost ``u`` and are skipped. The graph is built
with a small slack (a supergraph is still sound: its maximal cliques contain the true ones).

A clique subproblem's optimum is exact:

    ``f_C^* = min_{S subset C} [LS_S^* + cbar2 W(C \\ S)]``

with ``LS_S^*`` the weighted least-squares optimum on ``S``, closed form (weighted Procrustes),
because truncation only lowers a cost and the TLS optimum's inlier set attains it. A
branch-and-bound over "in"/"out" decisions finds it: a node with forced-in set ``I`` and
forced-out set ``O`` costs at least ``LS_I^* + cbar2 W(O)`` (least squares can only grow with
more terms). It is fast when the clique's optimum has few outliers and small residuals (the
high-outlier regime, where the maximal cliques are small); its node budget bounds the rest.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solvers.jit import compiled
from solvers.problem import WeightedTLSProblem

__all__ = [
    "consistency_edges",
    "candidate_cliques",
    "clique_number_bound",
    "small_clique_optimum",
    "CliqueOptimum",
    "clique_optimum",
]

log = logging.getLogger(__name__)

_EPS = float(np.finfo(np.float64).eps)


def consistency_edges(problem: WeightedTLSProblem, vertices: NDArray[np.int64]) -> NDArray[np.int64]:
    """Edges ``(i, j)``, ``i < j`` (positions in ``vertices``) of the consistency graph, with slack.

    Pairs with ``| ||a_ij|| - ||b_ij|| | <= cbar (beta_i + beta_j) (1 + 1e-9) + 8 eps (||a_ij|| +
    ||b_ij||)`` are joined: the slack covers the rounding of the lengths, so no pair of true
    inliers is ever left out (the pruning's graph, :func:`solvers.registration.pruning.consistency_graph`,
    with ``rounding_slack``).
    """
    from solvers.registration.pruning import consistency_edge_list

    return consistency_edge_list(problem.source[vertices], problem.target[vertices],
                                 problem.noise_bound[vertices], float(np.sqrt(problem.cbar2)),
                                 rounding_slack=True)


def _core(
    problem: WeightedTLSProblem, upper: float
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], int, float] | None:
    """Terms of positive weight ``act``, the ``(s_min - 1)``-core ``keep`` (positions in
    ``act``) of their consistency graph with its ``edges`` (positions in ``keep``), ``s_min``
    (the fewest terms a clique needs to weigh more than ``thr``) and ``thr``; ``None`` when
    no clique can beat ``upper`` (or the whole problem is one "clique": ``s_min = 0``)."""
    w = problem.weights
    act = np.flatnonzero(w > 0)
    c2 = problem.cbar2
    total = float(w.sum())
    # A clique of weight <= thr costs at least cbar2 (total - thr) >= upper; slack for rounding.
    thr = total - upper * (1 + 1e-9) / c2 - 1e-12 * total
    if act.size == 0 or thr < 0:
        return act, np.arange(act.size), np.empty((0, 2), dtype=np.int64), 0, thr
    ws = np.sort(w[act])[::-1]
    above = np.flatnonzero(np.cumsum(ws) > thr)
    if above.size == 0:
        return None
    s_min = int(above[0]) + 1
    edges = consistency_edges(problem, act)
    # Peel to the (s_min - 1)-core in numpy first: the core is usually tiny (high outlier
    # rates) or complete (low).
    alive = np.ones(act.size, dtype=bool)
    while True:
        live = alive[edges[:, 0]] & alive[edges[:, 1]]
        edges = edges[live]
        deg = np.bincount(edges.ravel(), minlength=act.size)
        drop = alive & (deg < s_min - 1)
        if not drop.any():
            break
        alive &= ~drop
    keep = np.flatnonzero(alive)
    if keep.size < s_min:
        return None
    remap = np.full(act.size, -1, dtype=np.int64)
    remap[keep] = np.arange(keep.size)
    return act, keep, remap[edges], s_min, thr


def _adjacency(m: int, edges: NDArray[np.int64]) -> NDArray[np.uint8]:
    adj = np.zeros((m, m), dtype=np.uint8)
    adj[edges[:, 0], edges[:, 1]] = 1
    adj[edges[:, 1], edges[:, 0]] = 1
    return adj


def candidate_cliques(
    problem: WeightedTLSProblem, upper: float, *, limit: int, max_nodes: int | None = None
) -> tuple[list[NDArray[np.int64]], bool]:
    """The maximal cliques ``C`` (indices of ``problem``) with ``cbar2 W(not C) < upper``.

    Only terms of positive weight are vertices (the others cost nothing anywhere). Returns the
    cliques sorted by decreasing weight and ``complete`` (False when there were more than
    ``limit``, or when the listing used up ``max_nodes`` branches: the list is then empty).
    Dense graphs (real features) can hold millions of maximal cliques: the listing is a
    compiled Bron-Kerbosch that stops at either limit, not a library call that lists them all.
    """
    core = _core(problem, upper)
    if core is None:
        return [], True
    act, keep, edges, s_min, thr = core
    if s_min == 0:
        return [act], True  # even the empty inlier set could beat `upper`
    m = keep.size
    if edges.shape[0] == m * (m - 1) // 2:
        return [act[keep]], True  # complete (low outlier rates): one clique
    heavy_maximal_cliques = compiled("solvers.certify._kernels").heavy_maximal_cliques

    w = np.ascontiguousarray(problem.weights[act[keep]])
    budget = np.iinfo(np.int64).max if max_nodes is None else int(max_nodes)
    flat, offsets, count, complete, nodes = heavy_maximal_cliques(
        _adjacency(m, edges), w, s_min, float(thr), int(limit), budget)
    if not complete:
        log.info("clique listing stopped (%d cliques, %d of %d nodes)", count, nodes, budget)
        return [], False
    found = [np.sort(act[keep[flat[offsets[k]:offsets[k + 1]]]]) for k in range(count)]
    found.sort(key=lambda c: -float(problem.weights[c].sum()))
    return found, True


def clique_number_bound(
    problem: WeightedTLSProblem, upper: float, *, max_work: int | None = None
) -> float:
    """A sound lower bound on the problem's optimum from the clique number alone.

    Every pose's strict inliers form a clique, so no pose keeps more than ``omega`` terms (the
    maximum clique of the consistency graph with slack) and its cost is at least
    ``cbar2 (W - the omega largest weights)``. Weak next to the clique decomposition, but it
    takes one maximum-clique search (milliseconds on dense graphs) rather than a listing of
    every maximal clique. When the search runs out of ``max_work``, ``omega`` is bounded by the
    core's size instead. Returns at most ``upper``.
    """
    from solvers.registration.pruning import maximum_cliques

    core = _core(problem, upper)
    if core is None:
        return float(upper)  # no clique beats `upper`: every pose costs at least it
    act, keep, edges, s_min, _ = core
    if act.size == 0:
        return 0.0
    if s_min == 0:  # every clique could beat `upper`: the whole graph
        keep, edges = np.arange(act.size), consistency_edges(problem, act)
    adj = _adjacency(keep.size, edges)
    cliques, exact = maximum_cliques(adj, limit=1, exact_max_vertices=None, max_work=max_work)
    omega = cliques[0].size if exact else keep.size
    # Cliques outside the core have fewer than s_min terms and cannot beat `upper`.
    ws = np.sort(problem.weights[act])[::-1]
    total = float(problem.weights.sum())
    lower = problem.cbar2 * (total - float(ws[:omega].sum()))
    lower -= 1e-12 * problem.cbar2 * total  # rounding of the sums
    return float(min(max(lower, 0.0), upper))


@dataclass(frozen=True)
class CliqueOptimum:
    """Outcome of :func:`clique_optimum` (costs in the subproblem's units).

    Attributes
    ----------
    lower_bound : float
        A sound lower bound on the subproblem's optimum (the exact optimum minus a rounding
        allowance when ``complete``; the least open node's bound otherwise).
    best_cost : float
        ``LS_S^* + cbar2 W(C \\ S)`` of the best inlier set found (an upper bound on the
        optimum: the true TLS cost of ``rotation``, ``translation`` is at most this).
    rotation, translation : ndarray
        The least-squares pose of the best inlier set.
    complete : bool
        The search finished within its node budget.
    nodes : int
        Branch-and-bound nodes evaluated.
    """

    lower_bound: float
    best_cost: float
    rotation: NDArray[np.float64]
    translation: NDArray[np.float64]
    complete: bool
    nodes: int


def small_clique_optimum(
    problem: WeightedTLSProblem, clique: NDArray[np.int64], rotation: NDArray[np.float64]
) -> CliqueOptimum:
    """Closed-form optimum of the subproblem of one or two terms ``clique`` (indices of
    ``problem``), with a pose attaining it.

    One term: 0 (the pose maps its source onto its target; ``rotation`` is kept). Two terms
    ``i, j`` with ``v = w / beta^2``: the least-squares optimum over rigid motions is
    ``v_i v_j / (v_i + v_j) (||a_j - a_i|| - ||b_j - b_i||)^2`` (the rotation aligns the two
    difference vectors, the translation matches the ``v``-weighted centroids, the length
    mismatch is split by weight), so the TLS minimum is the least of that and
    ``cbar2 min(w_i, w_j)`` (the lighter one an outlier; both outliers cost more). Only
    differences of the points enter, so offsets of the points do not round the bound.
    """
    from scipy.spatial.transform import Rotation

    clique = np.asarray(clique, dtype=np.int64)
    if not 1 <= clique.size <= 2:
        raise ValueError(f"Expected a clique of 1 or 2 terms, got {clique.size}.")
    a, b = problem.source[clique], problem.target[clique]
    w = problem.weights[clique]
    R = np.asarray(rotation, dtype=np.float64)
    if clique.size == 1:
        return CliqueOptimum(lower_bound=0.0, best_cost=0.0, rotation=R, translation=b[0] - R @ a[0],
                             complete=True, nodes=1)
    v = w / problem.noise_bound[clique] ** 2
    da_vec, db_vec = a[1] - a[0], b[1] - b[0]
    da, db = float(np.linalg.norm(da_vec)), float(np.linalg.norm(db_vec))
    mu = float(v[0] * v[1] / (v[0] + v[1])) if v[0] > 0 and v[1] > 0 else 0.0
    both = mu * (da - db) ** 2
    one_out = problem.cbar2 * float(w.min())
    if both <= one_out:
        if da > 0 and db > 0:
            R = Rotation.align_vectors(db_vec[None], da_vec[None])[0].as_matrix()
        vs = max(float(v.sum()), 1e-300)
        t = (v @ b) / vs - R @ ((v @ a) / vs)
        best = both
    else:
        k = int(np.argmax(w))
        t, best = b[k] - R @ a[k], one_out
    # Each length is exact to a few ulps of the coordinates it was computed from.
    mag = float(np.abs(a).max() + np.abs(b).max())
    delta = 16 * _EPS * (da + db + 4 * mag)
    allowance = mu * (2 * abs(da - db) * delta + delta**2) + 8 * _EPS * (both + one_out)
    return CliqueOptimum(lower_bound=float(max(min(both, one_out) - allowance, 0.0)),
                         best_cost=float(best), rotation=R, translation=t, complete=True, nodes=1)


NODES_PER_SECOND = 2_000_000
"""Branch-and-bound nodes per second (measured 2.2 M/s on one core of the 2-core test machine), for time limits."""

CHUNK_NODES = NODES_PER_SECOND // 20
"""Nodes per call of the compiled search (about 50 ms): it returns to Python between calls."""

ENUMERATE_MAX = 12
"""Cliques up to this size are solved by enumerating every inlier set at once (batched)."""


def _enumerated_optimum(problem: WeightedTLSProblem, upper: float) -> CliqueOptimum:
    """Exact optimum of a small problem: every inlier set's least squares, batched."""
    K = problem.n
    M = ((np.arange(1 << K)[:, None] >> np.arange(K)[None, :]) & 1).astype(np.float64)
    v = problem.weights / problem.noise_bound**2
    ca0 = (v @ problem.source) / max(v.sum(), 1e-300)
    cb0 = (v @ problem.target) / max(v.sum(), 1e-300)
    a, b = problem.source - ca0, problem.target - cb0
    V = M * v
    sw = V.sum(axis=1)
    safe = np.where(sw > 0, sw, 1.0)
    ca = (V @ a) / safe[:, None]
    cb = (V @ b) / safe[:, None]
    H = np.einsum("bk,ki,kj->bij", V, a, b) - sw[:, None, None] * ca[:, :, None] * cb[:, None, :]
    U, sv, Vt = np.linalg.svd(H)
    d = np.where(np.linalg.det(U @ Vt) > 0, 1.0, -1.0)
    aa = np.einsum("ki,ki->k", a, a)
    bb = np.einsum("ki,ki->k", b, b)
    ls = (V @ aa - sw * np.einsum("bi,bi->b", ca, ca) + V @ bb - sw * np.einsum("bi,bi->b", cb, cb)
          - 2 * (sv[:, 0] + sv[:, 1] + d * sv[:, 2]))
    ls = np.where(sw > 0, np.maximum(ls, 0.0), 0.0)
    g = ls + problem.cbar2 * ((1 - M) @ problem.weights)
    i = int(np.argmin(g))
    scale = float(v @ (aa + bb))
    allowance = 64 * _EPS * (scale + K * float(problem.weights.max(initial=0.0)) * problem.cbar2 + 1.0)
    R = Vt[i].T @ np.diag([1.0, 1.0, d[i]]) @ U[i].T
    t = cb[i] + cb0 - R @ (ca[i] + ca0)
    best = float(g[i])
    return CliqueOptimum(lower_bound=min(best, float(upper)) - allowance, best_cost=best,
                         rotation=R, translation=t, complete=True, nodes=int(M.shape[0]))


def clique_optimum(
    problem: WeightedTLSProblem,
    upper: float,
    order: NDArray[np.int64] | None = None,
    *,
    max_nodes: int = 20_000_000,
    time_limit: float | None = None,
) -> CliqueOptimum:
    """Exact optimum of a (small, nearly all-inlier) weighted TLS problem by branch and bound.

    Parameters
    ----------
    problem : WeightedTLSProblem
        The subproblem (e.g. one maximal clique).
    upper : float
        A known upper bound on its optimum (e.g. the candidate's cost on it): prunes the search.
    order : (K,) array of int, optional
        Branching order (default: as given). Deciding likely outliers first prunes sooner.
    max_nodes : int
        Node budget.
    time_limit : float or None
        Seconds.
    """
    K = problem.n
    if K <= ENUMERATE_MAX:
        return _enumerated_optimum(problem, upper)
    order = np.arange(K) if order is None else np.asarray(order, dtype=np.int64)
    # Each term in units of its noise bound: w/beta^2 |R a + t - b|^2 = |R a' + t' - b'|^2 * w/beta^2
    # does not factor (per-term beta), so the sums carry v = w / beta^2 explicitly.
    # Units of the median noise bound: least-squares values are unchanged, the sums stay
    # far from overflow and underflow at any scale of the points.
    unit = float(np.median(problem.noise_bound))
    v = (problem.weights / (problem.noise_bound / unit) ** 2)[order]
    a = problem.source[order] / unit
    b = problem.target[order] / unit
    # Centre for accuracy of the running-sum formula (a rigid shift keeps LS values).
    ca = (v @ a) / max(v.sum(), 1e-300)
    cb = (v @ b) / max(v.sum(), 1e-300)
    a, b = a - ca, b - cb
    wout = problem.cbar2 * problem.weights[order]
    # Rounding allowance of a value computed from the sums (cancellation in saa - sw |ca|^2).
    scale = float(v @ (np.einsum("ij,ij->i", a, a) + np.einsum("ij,ij->i", b, b)))
    allowance = 64 * _EPS * (scale + K * float(wout.max(initial=0.0)) + 1.0)
    clique_bnb = compiled("solvers.certify._kernels").clique_bnb  # numba: compiled on first use

    if time_limit is not None:
        # The compiled search cannot read the clock: the limit becomes a node budget.
        max_nodes = min(max_nodes, int(max(time_limit, 0.0) * NODES_PER_SECOND))
    a, b, v, wout = (np.ascontiguousarray(x) for x in (a, b, v, wout))
    state, out, phase = np.zeros((K + 1, 18)), np.zeros(K + 1), np.zeros(K + 1, dtype=np.int64)
    ints = np.zeros(3, dtype=np.int64)
    found_pose = np.zeros(13)
    found_pose[0] = float(upper)
    # In chunks of about 50 ms: between them Python runs, and Ctrl-C is answered.
    stop, code = 0, 1
    while code == 1:
        stop = min(stop + CHUNK_NODES, int(max_nodes))
        code = clique_bnb(a, b, v, wout, float(allowance), stop, int(max_nodes), state, out,
                          phase, ints, found_pose)
    best, complete, nodes, found = found_pose[0], code == 0, int(ints[1]), bool(ints[2])
    R, tp = found_pose[1:10].reshape(3, 3).copy(), found_pose[10:13].copy()
    if found:
        t = (cb - R @ ca + tp) * unit
        best_cost = float(best)
    else:
        R, t, best_cost = np.eye(3), np.zeros(3), np.inf
    # Complete: every inlier set is a visited leaf or in a pruned subtree, all >= best.
    # Stopped: unvisited siblings are bounded only by 0 (costs are non-negative).
    lower = float(best) - allowance if complete else 0.0
    return CliqueOptimum(lower_bound=float(lower), best_cost=float(best_cost), rotation=R,
                         translation=t, complete=complete, nodes=int(nodes))
