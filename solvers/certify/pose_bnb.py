"""A lower bound on the full weighted TLS problem by branch and bound over poses.

Why it is sound
---------------
Every pose ``(R, t)`` lies in a cell of rotation vectors (a cube inside ``[-pi, pi]^3``: the ball
of radius ``pi`` covers SO(3)) times translations (a cube), and a cell bounds the cost of each
of its poses from below (:func:`solvers.certify._pose_kernels.pose_bnb`: per-term residual
intervals, the least squares of the terms that are inliers throughout the cell, the
colouring bound of the pairwise-consistency graph: a pose's inliers are pairwise consistent, so
it keeps at most one term per colour class; and in small cells a convex relaxation of the cost
over the cell, every term at one pose, its rotation error second order in the cell's size:
:mod:`solvers.certify._convex_cell`). A depth-first search splits every cell whose bound
is below a threshold ``thr`` until its bound reaches ``thr`` or it has so few undecided terms
that its inlier sets are enumerated exactly (closed-form least squares per set, every pose of
the cell keeping its sure inliers). A complete search proves that no pose costs less than
``thr``. Poses outside the root translation cube keep no inlier of the core (every term's
inlier set is a ball of radius ``cbar beta`` about ``b_i - R a_i``, inside the cube): they cost
at least ``cbar2 W``. Terms outside the core of the consistency graph (no consistent set heavy
enough to beat ``thr`` contains them) are outliers of every pose that could: they enter as their
constant outlier cost (:func:`solvers.certify.cliques._core`).

What it costs
-------------
The cells are six-dimensional and the interval bound is per term (first order in the cell's
size), so the search grows quickly as ``thr`` approaches the optimum; near it the convex bound,
second order and joint, prunes most cells. :func:`pose_lower_bound` therefore raises ``thr`` in stages, from a
loose one (a large gap, a quick proof) towards the certificate's tolerance, without starting
again: the cells a stage leaves (pruned, or solved exactly) are kept with their bounds
(:class:`solvers.certify.pose_frontier.Frontier`), the next stage searches below only those still
under its threshold, lowest bound first, and the least bound of the kept cells is a proved
bound at any moment, so a stage the time limit stops still tightens it. The rotation and
translation are expressed about the candidate's inlier centroid, so rotations about it (the flat
directions of an inlier cluster seen from one side) barely move the terms that matter.
:func:`_stage` is the plain depth-first search against one threshold that the stages refine.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from solvers.certificate import undiluted_gap
from solvers.certify.pose_frontier import Frontier, _outlier_cost, stage_threshold
from solvers.jit import compiled
from solvers.problem import WeightedTLSProblem

__all__ = ["PoseBound", "pose_lower_bound", "frontier", "stage_threshold", "default_workers",
           "FRONTIER_GAPS", "STAGE_GAPS"]

log = logging.getLogger(__name__)

_EPS = float(np.finfo(np.float64).eps)

Refine = Callable[[WeightedTLSProblem, NDArray[np.float64], NDArray[np.float64]],
                  tuple[NDArray[np.float64], NDArray[np.float64]]]

STAGE_GAPS = (0.5, 0.3, 0.2, 0.1, 0.05, 0.02, 0.01, 0.005, 0.002)
"""Gaps of the depth-first stages, each a search from scratch (kept as the reference the tests
compare :data:`FRONTIER_GAPS`' search with)."""
FRONTIER_GAPS = (0.3, 0.2, 0.14, 0.1, 0.07, 0.05, 0.035, 0.025, 0.018, 0.012, 0.008, 0.005,
                 0.003, 0.002)
"""Gaps (:func:`solvers.certificate.undiluted_gap`) :func:`pose_lower_bound` proves in turn,
loosest first, before the certificate's own tolerance, each stage going on from the cells the
last one left."""

LEAF_TERMS = 8
"""Cells with at most this many undecided terms are solved exactly over their inlier sets."""
LEAF_NODES = 100
"""Node budget of one cell's exact solve (beyond it the cell is split instead)."""
RECOLOUR_MAX = 1000
"""Cells with at most this many possible inliers are recoloured with their own rotations."""
CHUNK_NODES = 50_000
"""Cells per call of the compiled search (it returns to Python to read the clock)."""
MAX_TERMS = 5000
"""Largest core the search takes on (its per-depth arrays hold ``MAX_DEPTH x`` the core's terms);
beyond it no stage is run."""
MAX_DEPTH = 200
"""Deepest cell of the search (a search that would go deeper stops incomplete)."""


@dataclass(frozen=True)
class PoseBound:
    """Outcome of :func:`pose_lower_bound` (costs in the problem's units).

    Attributes
    ----------
    lower : float
        A sound lower bound on the problem's minimum: the least bound of the cells left to
        search when the search stopped (``-inf`` when none was searched).
    proved_gap : float
        The gap of ``upper`` against ``lower`` (:func:`solvers.certificate.undiluted_gap`).
    upper : float
        The cost of the best pose known at the end: the candidate's, or a better pose's.
    rotation, translation : ndarray or None
        A pose better than the candidate found by the search (its least-squares pose of an
        inlier set), or None.
    complete : bool
        The stage at the certificate's tolerance completed.
    stages : list of (float, bool, int, float)
        Per stage tried: target gap, completed, cells visited, seconds.
    depth_profile : (D, 6) ndarray of int
        Per depth below the cell a search started from (all stages): cells visited, pruned
        by bounds, pruned by recolouring, solved exactly, given the convex bound, pruned by it
        (and not by the others).
    curve : list of (float, float)
        The lower bound after each pass over the kept cells: (seconds since the start, bound).
    """

    lower: float
    proved_gap: float
    upper: float
    rotation: NDArray[np.float64] | None
    translation: NDArray[np.float64] | None
    complete: bool
    stages: list[tuple[float, bool, int, float]] = field(default_factory=list)
    depth_profile: NDArray[np.int64] | None = None
    curve: list[tuple[float, float]] = field(default_factory=list)


def _colouring(m: int, edges: NDArray[np.int64]) -> NDArray[np.int64]:
    """A greedy colouring of the graph on ``m`` vertices, largest degree first: each vertex
    takes the smallest colour none of its coloured neighbours has."""
    both = np.concatenate([edges, edges[:, ::-1]]).reshape(-1, 2)
    both = both[np.argsort(both[:, 0], kind="stable")]
    start = np.searchsorted(both[:, 0], np.arange(m + 1))
    deg = np.diff(start)
    col = np.full(m, -1, dtype=np.int64)
    for i in np.argsort(-deg, kind="stable"):
        used = col[both[start[i]:start[i + 1], 1]]
        taken = np.zeros(deg[i] + 1, dtype=bool)
        taken[used[(used >= 0) & (used <= deg[i])]] = True
        col[i] = int(np.argmin(taken))  # the first free colour (one exists: deg + 1 slots)
    return col


def _bitsets(m: int, edges: NDArray[np.int64]) -> NDArray[np.uint64]:
    words = (m + 63) // 64
    bits = np.zeros((m, words), dtype=np.uint64)
    for i, j in ((edges[:, 0], edges[:, 1]), (edges[:, 1], edges[:, 0])):
        np.bitwise_or.at(bits, (i, j >> 6), np.left_shift(np.uint64(1), (j & 63).astype(np.uint64)))
    return bits


@dataclass
class _Search:
    """The compiled search's arrays for one threshold (fresh per stage)."""

    frames: NDArray[np.float64]
    act: NDArray[np.int64]
    cnt: NDArray[np.int64]
    outc: NDArray[np.float64]
    ccol: NDArray[np.int64]
    cinfo: NDArray[np.float64]
    ints: NDArray[np.int64]
    best: NDArray[np.float64]
    hist: NDArray[np.int64]


def _fresh(m: int, half_t: float, base: float, colour: NDArray[np.int64]) -> _Search:
    from solvers.certify._pose_kernels import FRAME_COLS

    frames = np.zeros((MAX_DEPTH, FRAME_COLS))
    frames[0, 3] = np.pi
    frames[0, 7] = half_t
    act = np.zeros((MAX_DEPTH, max(m, 1)), dtype=np.int64)
    act[0, :m] = np.arange(m)
    cnt = np.zeros(MAX_DEPTH, dtype=np.int64)
    cnt[0] = m
    outc = np.zeros(MAX_DEPTH)
    outc[0] = base
    best = np.zeros(14)
    best[0] = np.inf
    ccol = np.zeros((MAX_DEPTH, max(m, 1)), dtype=np.int64)
    ccol[0, :m] = colour
    cinfo = np.zeros((MAX_DEPTH, 3))
    cinfo[0] = (colour.max(initial=-1) + 1, np.inf, m)
    return _Search(frames, act, cnt, outc, ccol, cinfo, np.zeros(3, dtype=np.int64), best,
                   np.zeros((MAX_DEPTH, 6), dtype=np.int64))


@dataclass
class _StageResult:
    upper: float  # the best pose's cost (the candidate's unless the search found better)
    lower: float  # proved when complete: no pose costs less
    complete: bool
    cells: int
    profile: NDArray[np.int64] | None
    found: tuple[NDArray[np.float64], NDArray[np.float64]] | None


def pose_lower_bound(
    problem: WeightedTLSProblem, R: NDArray[np.float64], t: NDArray[np.float64], *, tol: float,
    time_limit: float, refine: Refine | None = None, workers: int | None = None,
) -> PoseBound:
    """Prove ``min f >= lower`` for the full problem by branch and bound over poses.

    Parameters
    ----------
    problem : WeightedTLSProblem
        The problem (normalised weights, as the certifier uses it).
    R : (3, 3) ndarray
    t : (3,) ndarray
        The candidate pose: its cost is the search's first upper bound.
    tol : float
        The certificate's tolerance on :func:`solvers.certificate.undiluted_gap`: the last
        stage's target.
    time_limit : float
        Seconds; the stages run while time remains. The bound is anytime: a stage stopped by
        the time limit still raises it (the least bound of the cells left to search).
    refine : callable, optional
        ``refine(problem, R, t) -> (R, t)``, a local refinement of a better pose the search
        finds (e.g. :func:`solvers.certify.refine_pose`); default: the least-squares pose of the
        inlier set it found, as is.
    workers : int, optional
        Threads searching the frontier's cells (default :func:`default_workers`).

    Returns
    -------
    PoseBound
    """
    t0 = time.perf_counter()
    deadline = t0 + time_limit
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    search = frontier(problem, R, t, refine=refine,
                      workers=default_workers() if workers is None else workers)
    if search.too_large:
        log.info("pose branch and bound: core of more than %d terms, not searched", MAX_TERMS)
    stages, complete = [], False
    for gap in [g for g in FRONTIER_GAPS if g > tol] + [tol]:
        if time.perf_counter() >= deadline or search.too_large or search.failed:
            break
        started, cells = time.perf_counter(), search.cells
        done = search.run(gap, deadline)
        stages.append((gap, done, search.cells - cells, time.perf_counter() - started))
        if not done:
            break
        complete = gap == tol
        log.info("pose branch and bound: gap %.3g proved in %d cells", gap, search.cells)
    u, found = search.u, search.found
    Rc, tc = found if found is not None else (R, t)
    lower = min(search.lower, u)
    return PoseBound(lower=float(lower),
                     proved_gap=float(undiluted_gap(u, lower, _outlier_cost(problem, Rc, tc))),
                     upper=float(u), rotation=None if found is None else found[0],
                     translation=None if found is None else found[1], complete=complete,
                     stages=stages, depth_profile=search.hist,
                     curve=[(s, min(lo, u)) for s, lo in search.curve])


def frontier(problem: WeightedTLSProblem, R: NDArray[np.float64], t: NDArray[np.float64], *,
             refine: Refine | None = None, workers: int = 2, cap: float | None = None
             ) -> Frontier:
    """The anytime search (:class:`solvers.certify.pose_frontier.Frontier`) for the candidate
    ``(R, t)``, with this module's core, frame and leaf settings (``cap``: as there)."""
    return Frontier(problem, R, t, lambda c: _setup(problem, R, t, c, c),
                    leaf_terms=LEAF_TERMS, leaf_nodes=LEAF_NODES, max_depth=MAX_DEPTH,
                    refine=refine, workers=workers, cap=cap)


def default_workers() -> int:
    """Threads of the search: the cores this process may run on, at most 4."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        n = os.cpu_count() or 1
    return max(1, min(n, 4))


def _stage(problem: WeightedTLSProblem, R: NDArray[np.float64], t: NDArray[np.float64],
           gap: float, remaining: float, refine: Refine | None = None) -> _StageResult:
    """One threshold's search (for a gap of ``gap`` to ``(R, t)``); when it finds a better
    pose it starts again against that pose, in what is left of ``remaining`` seconds."""
    t0 = time.perf_counter()
    kern = compiled("solvers.certify._pose_kernels").pose_bnb
    found = None
    u = problem.cost(R, t)
    while True:
        thr = stage_threshold(u, _outlier_cost(problem, R, t), gap)
        setup = _setup(problem, R, t, thr, u)
        if setup is None:  # no consistent set is heavy enough to go below thr
            return _StageResult(u, thr, True, 0, None, found)
        if isinstance(setup, str):
            log.info("pose branch and bound: core of more than %d terms, not searched", MAX_TERMS)
            return _StageResult(u, -np.inf, False, 0, None, found)
        args, unit, cs, ct, allowance, st = setup
        code = 1
        while code == 1:
            if time.perf_counter() - t0 >= remaining:
                return _StageResult(u, -np.inf, False, int(st.ints[1]), st.hist, found)
            code = kern(*args, float(thr), float(allowance), LEAF_TERMS, LEAF_NODES,
                        int(st.ints[1]) + CHUNK_NODES, np.iinfo(np.int64).max // 2, st.frames,
                        st.act, st.cnt, st.outc, st.ints, st.best, st.hist)
        if code == 0:
            return _StageResult(u, thr - allowance, True, int(st.ints[1]), st.hist, found)
        if code != 3:
            return _StageResult(u, -np.inf, False, int(st.ints[1]), st.hist, found)
        # A better pose: the least-squares pose of a cell's inlier set (centred frame),
        # refined; the search starts again against it.
        Rb = st.best[2:11].reshape(3, 3).copy()
        tb = st.best[11:14] * unit + ct - Rb @ cs
        if refine is not None:
            Rr, tr = refine(problem, Rb, tb)
            if problem.cost(Rr, tr) <= problem.cost(Rb, tb):
                Rb, tb = Rr, tr
        if not problem.cost(Rb, tb) < u:
            return _StageResult(u, -np.inf, False, int(st.ints[1]), st.hist, found)
        R, t, u, found = Rb, tb, problem.cost(Rb, tb), (Rb, tb)


def _setup(problem: WeightedTLSProblem, R: NDArray[np.float64], t: NDArray[np.float64],
           thr: float, u: float):  # noqa: ANN202
    """The compiled search's inputs for threshold ``thr``; None when the core is empty,
    ``"too_large"`` when it holds more than ``MAX_TERMS`` terms."""
    from solvers.certify.cliques import _core, consistency_edges

    core = _core(problem, thr)
    if core is None:
        return None
    act, keep, edges, s_min, _ = core
    if s_min == 0:
        keep = np.arange(act.size)
        edges = consistency_edges(problem, act)
    idx = act[keep]
    m = idx.size
    if m > MAX_TERMS:
        return "too_large"
    base = float(problem.cbar2 * (problem.weights.sum() - problem.weights[idx].sum()))
    unit = float(np.median(problem.noise_bound[idx])) if m else 1.0
    # About the candidate's inlier centroid and its image (see the module docstring).
    inl = problem.residuals_sq(R, t) < problem.cbar2
    v_all = problem.weights / problem.noise_bound**2
    cs = ((v_all[inl] @ problem.source[inl]) / v_all[inl].sum() if v_all[inl].sum() > 0
          else problem.source.mean(axis=0))
    ct = R @ cs + t
    a = np.ascontiguousarray((problem.source[idx] - cs) / unit)
    b = np.ascontiguousarray((problem.target[idx] - ct) / unit)
    v = np.ascontiguousarray(problem.weights[idx] / (problem.noise_bound[idx] / unit) ** 2)
    wout = np.ascontiguousarray(problem.cbar2 * problem.weights[idx])
    anorm = np.linalg.norm(a, axis=1)
    bnorm = np.linalg.norm(b, axis=1)
    pair_tol = np.ascontiguousarray(np.sqrt(problem.cbar2) * problem.noise_bound[idx] / unit
                                    * (1 + 1e-9))
    # Every inlier's translation lies within this cube (module docstring).
    half_t = float((anorm.max(initial=0.0) + bnorm.max(initial=0.0)
                    + pair_tol.max(initial=0.0)) * (1 + 1e-9) + 1e-9)
    slack = np.ascontiguousarray(64 * _EPS * (anorm + bnorm + 2 * half_t + 1.0))
    scale = float(v @ (anorm**2 + bnorm**2))
    allowance = 64 * _EPS * (scale + float(wout.sum()) + 1.0) + 1e-12 * (1 + abs(u))
    st = _fresh(m, half_t, base, _colouring(m, edges))
    args = (a, b, v, wout, anorm, slack, pair_tol, st.ccol, st.cinfo, _bitsets(m, edges),
            RECOLOUR_MAX)
    return args, unit, cs, ct, allowance, st
