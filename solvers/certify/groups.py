"""A lower bound on weighted TLS from the correspondences that share a source point.

Why it is sound
---------------
Correspondences ``k = (a_k, b_k)`` with the same source point ``a`` share its image
``q = R a + t``. Let every distinct source point's image move freely (drop the rigid motion):

    ``f(R, t) = sum_g sum_{k in g} w_k min(||b_k - q_g||^2 / beta_k^2, cbar2)
              >= sum_g min_q sum_{k in g} w_k min(||b_k - q||^2 / beta_k^2, cbar2)``.

Each group's minimum is exact over its inlier subsets ``S``:

    ``min_q [...] = min_S [min_q sum_{k in S} a_k ||b_k - q||^2 + cbar2 W(g \\ S)]``,
    ``a_k = w_k / beta_k^2``,

whose inner minimum lies at the ``a``-weighted mean of ``b_S`` (closed form); truncation only
lowers a term, and the minimiser's own inlier set attains it. A group of one contributes 0.
Groups of more than :data:`ENUMERATE_MAX` correspondences are split into chunks of nearby
targets; each chunk gets its own image, so the chunks' minima sum to at most the group's.

Pairs of source points put some of the rigid motion back: ``||q_i - q_j|| = ||a_i - a_j|| = d``
for any rigid motion, and for inlier subsets ``S_i``, ``S_j`` with weights ``A_i``, ``A_j`` and
weighted means ``m_i``, ``m_j``,

    ``min_{||q_i - q_j|| = d} A_i ||q_i - m_i||^2 + A_j ||q_j - m_j||^2
      = A_i A_j / (A_i + A_j) (||m_i - m_j|| - d)^2``

(the pair's midpoint free, its difference on a sphere of radius ``d``). Over disjoint pairs (a
matching of the groups, chosen greedily by what each pair adds) and the groups left alone, the
sum of the minima is still a lower bound, and never below the groups' own.

Where it helps: eq. (2)'s problems (``k`` candidate voxels per model point) are dense graphs
whose maximal cliques are too many to bound one by one; their correspondences come in groups,
and this bound says how far from optimal a pose can be at most (the rigid motion is what it
leaves out). One-to-one correspondences give the trivial 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from solvers.problem import WeightedTLSProblem

__all__ = ["ENUMERATE_MAX", "SharedSourceBound", "shared_source_bound"]

#: Largest group whose inlier subsets are enumerated (2^12 - 1 of them); larger ones are chunked.
ENUMERATE_MAX = 12

# Elements (groups x subsets) per batch of the enumeration: bounds the memory to ~10^2 MB.
_BATCH_ELEMENTS = 2_000_000


@dataclass(frozen=True)
class SharedSourceBound:
    """Result of :func:`shared_source_bound`.

    Attributes
    ----------
    lower : float
        Lower bound on the problem's minimum (its units), less a rounding allowance; ``>= 0``.
    groups : int
        Distinct source points with more than one correspondence (the ones that contribute).
    chunked : int
        Of those, groups split into chunks of at most :data:`ENUMERATE_MAX` (a weaker bound).
    pairs : int
        Pairs of groups bounded together (their distance kept).
    """

    lower: float
    groups: int
    chunked: int
    pairs: int = 0


def _subsets(k: int) -> NDArray[np.float64]:
    """(2^k - 1, k) indicator rows of the non-empty subsets of ``k`` items."""
    codes = np.arange(1, 1 << k, dtype=np.int64)
    return ((codes[:, None] >> np.arange(k)) & 1).astype(np.float64)


def _subset_tables(b: NDArray[np.float64], a: NDArray[np.float64], w: NDArray[np.float64],
                   cbar2: float) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Every inlier subset of ``G`` groups of ``k`` correspondences (``b`` (G, k, 3) targets,
    ``a`` (G, k) ``w_k / beta_k^2``, ``w`` (G, k)): its ``a``-weighted mean (G, S, 3), total
    ``a`` (G, S) and cost at that mean, outliers included (G, S); the last subset is the empty
    one (weight 0). A group's minimum over a free image is the least cost."""
    G, k = a.shape
    mean = b.mean(axis=1, keepdims=True)
    b = b - mean  # centred: less cancellation in S2 - |S1|^2 / SA
    M = _subsets(k)
    centre = np.zeros((G, M.shape[0] + 1, 3))
    weight = np.zeros((G, M.shape[0] + 1))
    const = np.empty((G, M.shape[0] + 1))
    const[:, -1] = cbar2 * w.sum(axis=1)
    step = max(1, _BATCH_ELEMENTS // M.shape[0])
    for s in range(0, G, step):
        bb, aa, ww = b[s:s + step], a[s:s + step], w[s:s + step]
        SA = aa @ M.T
        S1 = np.einsum("gk,gkd,sk->gsd", aa, bb, M)
        S2 = (aa * np.einsum("gkd,gkd->gk", bb, bb)) @ M.T
        centre[s:s + step, :-1] = S1 / SA[..., None] + mean[s:s + step]
        weight[s:s + step, :-1] = SA
        const[s:s + step, :-1] = (np.maximum(S2 - np.einsum("gsd,gsd->gs", S1, S1) / SA, 0.0)
                                  + cbar2 * (ww.sum(axis=1, keepdims=True) - ww @ M.T))
    return centre, weight, const


def _group_minima(b: NDArray[np.float64], a: NDArray[np.float64], w: NDArray[np.float64],
                  cbar2: float) -> NDArray[np.float64]:
    """(G,) exact ``min_q sum_k w_k min(a_k/w_k ||b_k - q||^2, cbar2)`` of ``G`` groups of ``k``
    correspondences each (arguments as :func:`_subset_tables`')."""
    return _subset_tables(b, a, w, cbar2)[2].min(axis=1)


def _pair_minimum(ci: NDArray[np.float64], wi: NDArray[np.float64], ki: NDArray[np.float64],
                  cj: NDArray[np.float64], wj: NDArray[np.float64], kj: NDArray[np.float64],
                  d: float, *, kernel: Any = None) -> float:
    """Exact minimum of two groups' costs with their images ``d`` apart (module docstring), from
    their subset tables (centres, weights, costs). Only subsets that can beat the least value
    found so far are tried, the cheapest few of each group first. A numba kernel
    (``kernel``: the compiled ``pair_minimum``, looked up once by a caller of many pairs): the
    values of the numpy form, bit for bit, and about ten times faster on eq. (2)'s problems
    (measured on 2,228 pairs of three YCB-Video pairs' certificates: 0.46 -> 0.05 s), where the
    pairs were most of a certification's time, spent holding the GIL beside the MLE's search."""
    if kernel is None:
        from solvers.jit import compiled

        kernel = compiled("solvers.certify._kernels").pair_minimum
    c = np.ascontiguousarray
    return float(kernel(c(ci, dtype=np.float64), c(wi, dtype=np.float64), c(ki, dtype=np.float64),
                        c(cj, dtype=np.float64), c(wj, dtype=np.float64), c(kj, dtype=np.float64),
                        float(d), _FEW))


_FEW = 12  # subsets per group tried first in a pair (see _pair_minimum)

#: Pairs are bounded when the groups are at most this many.
PAIR_GROUPS_MAX = 400


def _greedy_pairs(tables: list[tuple[NDArray[np.float64], ...]], sources: NDArray[np.float64],
                  singles: NDArray[np.float64]) -> tuple[float, int]:
    """What a greedy matching of the groups adds to their own minima (any matching is sound),
    and how many pairs it holds.

    Lazily: a pair's gain is at most that of its two best subsets placed ``d`` apart, the
    heap's first key; its exact gain is computed only when it comes on top with both groups
    still free, and pushed back (keys only fall), so the pairs are taken in the order of
    their exact gains without computing most of them."""
    import heapq

    from solvers.jit import compiled

    kernel = compiled("solvers.certify._kernels").pair_minimum
    n = len(tables)
    best = [int(np.argmin(t[2])) for t in tables]
    centre = np.array([t[0][k] for t, k in zip(tables, best, strict=True)])
    weight = np.array([t[1][k] for t, k in zip(tables, best, strict=True)])
    i, j = np.triu_indices(n, 1)
    d = np.linalg.norm(sources[i] - sources[j], axis=1)
    mu = np.where((weight[i] > 0) & (weight[j] > 0),
                  weight[i] * weight[j] / np.maximum(weight[i] + weight[j], 1e-300), 0.0)
    estimate = mu * (np.linalg.norm(centre[i] - centre[j], axis=1) - d) ** 2
    heap = [(-float(e), int(a), int(b), False) for e, a, b in zip(estimate, i, j, strict=True)
            if e > 0]
    heapq.heapify(heap)
    used = np.zeros(n, dtype=bool)
    added, count = 0.0, 0
    while heap:
        key, a, b, exact = heapq.heappop(heap)
        if used[a] or used[b]:
            continue
        if exact:
            used[a] = used[b] = True
            added, count = added - key, count + 1
            continue
        gain = (_pair_minimum(*tables[a], *tables[b], float(np.linalg.norm(sources[a] - sources[b])),
                              kernel=kernel)
                - singles[a] - singles[b])
        if gain > 0:
            heapq.heappush(heap, (-gain, a, b, True))
    return added, count


def _chunks(b: NDArray[np.float64], idx: NDArray[np.int64]) -> list[NDArray[np.int64]]:
    """Split ``idx`` into runs of at most ENUMERATE_MAX along the targets' principal axis."""
    y = b[idx] - b[idx].mean(axis=0)
    axis = np.linalg.svd(y, full_matrices=False)[2][0]
    order = idx[np.argsort(y @ axis, kind="stable")]
    n = -(-len(order) // ENUMERATE_MAX)
    return list(np.array_split(order, n))


def shared_source_bound(problem: WeightedTLSProblem, *, pairs: bool = True) -> SharedSourceBound:
    """Lower bound on a weighted TLS problem's minimum from its correspondences that share a
    source point (module docstring), in the problem's units.

    Parameters
    ----------
    problem : WeightedTLSProblem
    pairs : bool
        Also bound pairs of groups with their distance kept (at most :data:`PAIR_GROUPS_MAX`
        groups, none chunked): tighter, and 0.1 s on eq. (2)'s problems of about 50 groups.

    Returns
    -------
    SharedSourceBound
        ``lower`` is 0 when no two correspondences share a source point.
    """
    # Terms of weight 0 cost nothing anywhere (and would make empty-weight subsets 0 / 0).
    live = problem.weights > 0
    # Coordinates about a local origin: the pairs' distances are then differences of small
    # numbers, not of large offsets (the allowance below still covers what is left).
    a_src = problem.source[live] - np.median(problem.source[live], axis=0) if live.any() else None
    if a_src is None:
        return SharedSourceBound(lower=0.0, groups=0, chunked=0)
    _, inv, counts = np.unique(a_src, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    multi = np.flatnonzero(counts > 1)
    if multi.size == 0:
        return SharedSourceBound(lower=0.0, groups=0, chunked=0)
    b = problem.target[live] - np.median(problem.target[live], axis=0)
    w = problem.weights[live]
    a = w / problem.noise_bound[live] ** 2
    order = np.argsort(inv, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)])
    pieces: list[NDArray[np.int64]] = []
    chunked = 0
    for g in multi:
        idx = order[starts[g]:starts[g + 1]]
        if idx.size > ENUMERATE_MAX:
            chunked += 1
            pieces.extend(_chunks(b, idx))
        else:
            pieces.append(idx)
    total, scale = 0.0, 0.0
    by_size: dict[int, list[NDArray[np.int64]]] = {}
    for idx in pieces:
        by_size.setdefault(int(idx.size), []).append(idx)
    use_pairs = pairs
    whole = {int(inv[idx[0]]) for idx in pieces} if chunked == 0 else set()
    tables: list[tuple[NDArray[np.float64], ...]] = []  # per whole group, for the pairs
    sources: list[NDArray[np.float64]] = []
    singles: list[float] = []
    for k, group in by_size.items():
        if k < 2:
            continue  # one correspondence alone can always be an inlier at zero cost
        rows = np.stack(group)
        centre, weight, const = _subset_tables(b[rows], a[rows], w[rows], problem.cbar2)
        best = const.min(axis=1)
        total += float(best.sum())
        centred = b[rows] - b[rows].mean(axis=1, keepdims=True)
        scale += float((a[rows] * np.einsum("gkd,gkd->gk", centred, centred)).sum()
                       + problem.cbar2 * w[rows].sum())
        for r, idx in enumerate(group):
            if int(inv[idx[0]]) in whole:
                tables.append((np.ascontiguousarray(centre[r]), np.ascontiguousarray(weight[r]),
                               np.ascontiguousarray(const[r])))
                sources.append(a_src[idx[0]])
                singles.append(float(best[r]))
    pairs = 0
    eps = float(np.finfo(np.float64).eps)
    pair_allowance = 0.0
    if use_pairs and 2 <= len(tables) <= PAIR_GROUPS_MAX:
        added, pairs = _greedy_pairs(tables, np.asarray(sources), np.asarray(singles))
        total += added
        # A pair's value mu (D - d)^2 rounds through its distances D (between weighted means
        # of targets) and d (between sources), each exact to a few ulps of the coordinates'
        # magnitude M; mu is at most a group's total weight.
        M = 2 * (float(np.abs(b).max()) + float(np.abs(a_src).max())) * np.sqrt(3)
        delta = 16 * eps * M
        mu_max = max(float(t[1].max()) for t in tables)
        pair_allowance = pairs * mu_max * (2 * M * delta + delta**2)
    # Rounding allowance: each minimum is exact up to a few ulps of its terms' magnitude.
    kmax = max(by_size)
    lower = max(total - 64 * kmax * eps * (1.0 + scale) - pair_allowance, 0.0)
    return SharedSourceBound(lower=float(lower), groups=int(multi.size), chunked=chunked,
                             pairs=pairs)
