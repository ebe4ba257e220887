"""Is a consensus larger than random correspondences would give? (a non-randomness test)

A TLS optimum always keeps *some* correspondences: three random ones are mutually consistent
with a pose more often than not. Following the a contrario tests of the RANSAC literature (the
"number of false alarms" of Moisan and Stival's ORSA, PROSAC's non-randomness criterion), a
consensus of ``k`` out of ``N`` correspondences is compared with the expected number of
``k``-subsets of ``N`` *random* correspondences (the same points, paired at random, the same
noise bounds) that are pairwise consistent::

    NFA(k) = C(N, k) * q ** C(k, 2)

where ``q`` is the probability that two random correspondences pass the pairwise-consistency
test of the max-clique pruning (``| ||b_i - b_j|| - ||a_i - a_j|| | <= cbar (beta_i +
beta_j)``), which every pair of true inliers passes. Every set of inliers of one pose is such a
subset, so ``NFA(k) < 1`` says random data would not be expected to contain a consensus that
large; ``NFA(k) >= 1`` says the consensus is no evidence of a correct registration, whatever
the optimality certificate says about the TLS cost. Edges are treated as independent (an
Erdos-Renyi approximation of the consistency graph).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solvers.problem import WeightedTLSProblem

__all__ = ["Significance", "consensus_significance", "pair_probability"]

_PAIRS = 2048
"""Random pairs per side when ``q`` is estimated (all pairs below this many)."""


@dataclass(frozen=True)
class Significance:
    """Outcome of :func:`consensus_significance`.

    Attributes
    ----------
    consensus : int
        Correspondences kept (inliers of positive weight).
    n : int
        Correspondences given.
    pair_probability : float
        ``q``: probability that two randomly paired correspondences are pairwise consistent.
    log10_nfa : float
        ``log10`` of the expected number of pairwise-consistent ``consensus``-subsets among
        ``n`` random correspondences (``-inf`` when ``q`` is 0).
    significant : bool
        ``log10_nfa < 0``: fewer than one such subset expected by chance.
    """

    consensus: int
    n: int
    pair_probability: float
    log10_nfa: float
    significant: bool

    def describe(self) -> str:
        """One sentence for a result's message."""
        nfa = 10.0 ** self.log10_nfa if self.log10_nfa < 300 else math.inf
        return (f"{self.consensus} of {self.n} correspondences agree, no more than random "
                f"correspondences with this noise bound would give (two random ones are "
                f"consistent with probability {self.pair_probability:.2g}; expected number of "
                f"random consistent sets this large: {nfa:.3g})")


def _pair_lengths(points: NDArray[np.float64], i: NDArray[np.int64],
                  j: NDArray[np.int64]) -> NDArray[np.float64]:
    d = points[i] - points[j]
    return np.sqrt(np.einsum("ij,ij->i", d, d))


def _pairs(n: int, rng: np.random.Generator,
           pairs: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Index pairs ``i != j``: all of them when few, else ``pairs`` random ones."""
    if n * (n - 1) // 2 <= pairs:
        return np.triu_indices(n, 1)
    i = rng.integers(0, n, pairs)
    j = (i + rng.integers(1, n, pairs)) % n  # never i
    return i, j


def pair_probability(problem: WeightedTLSProblem, *, pairs: int = _PAIRS) -> float:
    """``q``: the probability that a random source pair and a random target pair pass the
    pairwise-consistency test (the correspondences' pairing destroyed, the points and noise
    bounds kept). Estimated from fixed random pairs (reproducible), exactly when few."""
    rng = np.random.default_rng(0)
    src, dst = problem.source, problem.target
    beta = problem.noise_bound
    cbar = math.sqrt(problem.cbar2)
    si, sj = _pairs(problem.n, rng, pairs)
    ti, tj = _pairs(problem.n, rng, pairs)
    ds = _pair_lengths(src, si, sj)
    tau = cbar * (beta[si] + beta[sj])
    dt = np.sort(_pair_lengths(dst, ti, tj))
    hits = np.searchsorted(dt, ds + tau, side="right") - np.searchsorted(dt, ds - tau, side="left")
    return float(hits.sum()) / (ds.size * dt.size)


def consensus_significance(problem: WeightedTLSProblem, inliers: NDArray[np.bool_]) -> Significance:
    """Whether the consensus ``inliers`` (N,) of ``problem`` beats random correspondences.

    See the module docstring for the test. Correspondences of zero weight are not counted.
    """
    keep = np.asarray(inliers, dtype=bool) & (problem.weights > 0)
    k, n = int(np.count_nonzero(keep)), problem.n
    log_c = (math.lgamma(n + 1) - math.lgamma(k + 1) - math.lgamma(n - k + 1)) / math.log(10)

    def log_nfa(q: float) -> float:
        if q <= 0.0:
            return -math.inf if k >= 2 else log_c
        return log_c + (k * (k - 1) / 2) * math.log10(min(q, 1.0))

    # A large consensus is significant by far: a coarse q (a tenth of the pairs), taken twice
    # as large, settles it at a tenth of the cost.
    q = pair_probability(problem, pairs=_PAIRS // 8)
    if log_nfa(2.0 * q) >= 0.0:
        q = pair_probability(problem)
    value = log_nfa(q)
    return Significance(k, n, q, value, bool(value < 0.0))
