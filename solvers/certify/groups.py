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

Where it helps: eq. (2)'s problems (``k`` candidate voxels per model point) are dense graphs
whose maximal cliques are too many to bound one by one; their correspondences come in groups,
and this bound says how far from optimal a pose can be at most (the rigid motion is what it
leaves out). One-to-one correspondences give the trivial 0.
"""

from __future__ import annotations

from dataclasses import dataclass

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
    """

    lower: float
    groups: int
    chunked: int


def _subsets(k: int) -> NDArray[np.float64]:
    """(2^k - 1, k) indicator rows of the non-empty subsets of ``k`` items."""
    codes = np.arange(1, 1 << k, dtype=np.int64)
    return ((codes[:, None] >> np.arange(k)) & 1).astype(np.float64)


def _group_minima(b: NDArray[np.float64], a: NDArray[np.float64], w: NDArray[np.float64],
                  cbar2: float) -> NDArray[np.float64]:
    """(G,) exact ``min_q sum_k w_k min(a_k/w_k ||b_k - q||^2, cbar2)`` of ``G`` groups of ``k``
    correspondences each: ``b`` (G, k, 3) targets, ``a`` (G, k) ``w_k / beta_k^2``, ``w`` (G, k)."""
    G, k = a.shape
    b = b - b.mean(axis=1, keepdims=True)  # centred: less cancellation in S2 - |S1|^2 / SA
    M = _subsets(k)
    out = cbar2 * w.sum(axis=1)  # the empty inlier set
    step = max(1, _BATCH_ELEMENTS // M.shape[0])
    for s in range(0, G, step):
        bb, aa, ww = b[s:s + step], a[s:s + step], w[s:s + step]
        SA = aa @ M.T
        S1 = np.einsum("gk,gkd,sk->gsd", aa, bb, M)
        S2 = (aa * np.einsum("gkd,gkd->gk", bb, bb)) @ M.T
        ls = np.maximum(S2 - np.einsum("gsd,gsd->gs", S1, S1) / SA, 0.0)
        val = ls + cbar2 * (ww.sum(axis=1, keepdims=True) - ww @ M.T)
        out[s:s + step] = np.minimum(out[s:s + step], val.min(axis=1))
    return out


def _chunks(b: NDArray[np.float64], idx: NDArray[np.int64]) -> list[NDArray[np.int64]]:
    """Split ``idx`` into runs of at most ENUMERATE_MAX along the targets' principal axis."""
    y = b[idx] - b[idx].mean(axis=0)
    axis = np.linalg.svd(y, full_matrices=False)[2][0]
    order = idx[np.argsort(y @ axis, kind="stable")]
    n = -(-len(order) // ENUMERATE_MAX)
    return list(np.array_split(order, n))


def shared_source_bound(problem: WeightedTLSProblem) -> SharedSourceBound:
    """Lower bound on a weighted TLS problem's minimum from its correspondences that share a
    source point (module docstring), in the problem's units.

    Parameters
    ----------
    problem : WeightedTLSProblem

    Returns
    -------
    SharedSourceBound
        ``lower`` is 0 when no two correspondences share a source point.
    """
    a_src = problem.source
    _, inv, counts = np.unique(a_src, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    multi = np.flatnonzero(counts > 1)
    if multi.size == 0:
        return SharedSourceBound(lower=0.0, groups=0, chunked=0)
    b, w = problem.target, problem.weights
    a = w / problem.noise_bound**2
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
    for k, group in by_size.items():
        if k < 2:
            continue  # one correspondence alone can always be an inlier at zero cost
        rows = np.stack(group)
        total += float(_group_minima(b[rows], a[rows], w[rows], problem.cbar2).sum())
        centred = b[rows] - b[rows].mean(axis=1, keepdims=True)
        scale += float((a[rows] * np.einsum("gkd,gkd->gk", centred, centred)).sum()
                       + problem.cbar2 * w[rows].sum())
    # Rounding allowance: each minimum is exact up to a few ulps of its terms' magnitude.
    kmax = max(by_size)
    lower = max(total - 64 * kmax * np.finfo(np.float64).eps * (1.0 + scale), 0.0)
    return SharedSourceBound(lower=float(lower), groups=int(multi.size), chunked=chunked)
