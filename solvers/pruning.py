"""Outlier pruning for extreme outlier rates (TEASER++-style).

Pairwise consistency of translation-invariant measurements gives a graph whose maximum clique
holds the mutually consistent correspondences; translation is then voted exactly per component.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import ArrayLike, NDArray


__all__ = ["consistency_graph_edges", "max_clique", "scalar_tls", "prune_max_clique"]

log = logging.getLogger(__name__)


def consistency_graph_edges(
    source: ArrayLike, target: ArrayLike, noise_bound: ArrayLike, cbar: float = 1.0
) -> NDArray[np.int64]:
    """Edges ``(i, j)``, ``i < j``, of the pairwise-consistency graph.

    Correspondences ``i`` and ``j`` are consistent when the lengths of the translation-invariant
    measurements ``a_j - a_i`` and ``b_j - b_i`` differ by at most ``cbar (beta_i + beta_j)``,
    which holds for every pair of inliers.

    Returns
    -------
    (E, 2) ndarray of int64
    """
    a = np.ascontiguousarray(source, dtype=np.float64)
    b = np.ascontiguousarray(target, dtype=np.float64)
    beta = np.ascontiguousarray(np.broadcast_to(noise_bound, (a.shape[0],)), dtype=np.float64)
    from solvers import _kernels  # numba: imported on first solve

    return _kernels.consistency_edges(a, b, beta, float(cbar))


def max_clique(n: int, edges: NDArray[np.int64]) -> NDArray[np.int64]:
    """Vertices of one maximum clique of an undirected graph (igraph's exact Cliquer search).

    Parameters
    ----------
    n : int
        Number of vertices.
    edges : (E, 2) int array
        Undirected edges.

    Returns
    -------
    (m,) ndarray of int64
        Sorted vertex indices of a largest clique (a single vertex when there are no edges).
    """
    import igraph as ig

    if n == 0:
        return np.empty(0, dtype=np.int64)
    if len(edges) == 0:
        return np.zeros(1, dtype=np.int64)
    g = ig.Graph(n=n, edges=edges, directed=False)
    # k-core pruning: a clique of size m lives inside the (m-1)-core; shrink the search graph.
    cores = np.asarray(g.coreness())
    kmax = int(cores.max())
    keep = np.flatnonzero(cores >= kmax)
    best: list[int] = []
    # Try the densest core first; its clique bounds what the rest can offer.
    for k in range(kmax, 0, -1):
        if len(best) >= k + 1:
            break
        keep = np.flatnonzero(cores >= k)
        sub = g.induced_subgraph(keep.tolist())
        clique = sub.largest_cliques()[0] if sub.ecount() else [0]
        if len(clique) > len(best):
            best = [int(keep[v]) for v in clique]
        if len(best) >= k + 1:
            break
    return np.sort(np.asarray(best, dtype=np.int64))


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
    v = np.asarray(values, dtype=np.float64).ravel()
    n = v.size
    beta = np.broadcast_to(np.asarray(noise_bound, dtype=np.float64), (n,))
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    cbar = np.sqrt(cbar2)
    ends = np.concatenate([v - beta * cbar, v + beta * cbar])
    sign = np.concatenate([np.ones(n), -np.ones(n)])
    idx = np.concatenate([np.arange(n), np.arange(n)])
    order = np.argsort(ends, kind="stable")
    ends, sign, idx = ends[order], sign[order], idx[order]
    p = w[idx] / beta[idx] ** 2
    # Running sums of the active quadratic terms after each endpoint.
    s0 = np.cumsum(sign * p)
    s1 = np.cumsum(sign * p * v[idx])
    s2 = np.cumsum(sign * p * v[idx] ** 2)
    n_active_w = np.cumsum(sign * w[idx])
    total_w = w.sum()
    # Piece k spans [ends[k], ends[k+1]].
    lo, hi = ends[:-1], ends[1:]
    s0, s1, s2, aw = s0[:-1], s1[:-1], s2[:-1], n_active_w[:-1]
    with np.errstate(invalid="ignore", divide="ignore"):
        x = np.where(s0 > 0, s1 / np.where(s0 > 0, s0, 1.0), lo)
    x = np.clip(x, lo, hi)
    cost = s0 * x**2 - 2 * s1 * x + s2 + (total_w - aw) * cbar2
    k = int(np.argmin(cost))
    if not np.isfinite(cost[k]) or cost[k] >= total_w * cbar2:
        # No piece beats "everything is an outlier": any x is optimal; use the weighted median.
        return float(np.median(v)), float(total_w * cbar2)
    return float(x[k]), float(cost[k])


def prune_max_clique(
    source: NDArray[np.float64],
    target: NDArray[np.float64],
    noise_bound: NDArray[np.float64],
    cbar2: float = 1.0,
) -> tuple[NDArray[np.int64], int]:
    """Indices of the maximum consistent set and the number of graph edges."""
    edges = consistency_graph_edges(source, target, noise_bound, np.sqrt(cbar2))
    clique = max_clique(source.shape[0], edges)
    log.debug("consistency graph: %d vertices, %d edges, max clique %d",
              source.shape[0], len(edges), clique.size)
    return clique, len(edges)
