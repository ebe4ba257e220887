"""The branch and bound over poses run as an anytime search that keeps its frontier.

A depth-first search against a threshold ``thr`` (:func:`solvers.certify._pose_kernels.pose_bnb`)
leaves every cell it did not split with a bound: pruned cells (bound at least ``thr``) and cells
solved exactly. :class:`Frontier` records those cells (their cubes, bounds and the terms still
possible in their parents), so the next, higher threshold searches below only the recorded cells
whose bound is below it, the lowest first, instead of starting again from the root: no work of
an earlier stage is redone. The recorded cells cover every pose that could cost less than the
candidate, so the least of their bounds is a lower bound at any moment (anytime), and it rises
as the search goes on. The cells of one stage are independent: worker threads take them in
blocks, each with its own search state, the compiled kernel releasing the GIL.

The core (:func:`solvers.certify.cliques._core`) is taken once, against the candidate's cost:
a term outside it is an outlier of every pose costing less than the candidate, so every bound
holds for those poses (a better pose found later costs less still).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from solvers.jit import compiled
from solvers.problem import WeightedTLSProblem

__all__ = ["Frontier", "stage_threshold"]

CHUNK_NODES = 20_000
"""Cells per call of the compiled search (it returns to Python to read the clock)."""
SPLIT_DEPTH = 6
"""Levels a search goes below one of the frontier's cells before it leaves the cells there to
a later pass (so that the workers share the deep searches near the optimum)."""
COMPACT_ROWS = 1 << 25
"""Rows of the term pool beyond which it is compacted (when most of it is dead)."""
FIRST_ROWS = 1 << 15
"""Initial rows of a worker's record buffer (doubled when full)."""

Refine = Callable[[WeightedTLSProblem, NDArray[np.float64], NDArray[np.float64]],
                  tuple[NDArray[np.float64], NDArray[np.float64]]]


@dataclass
class _Worker:
    """One thread's search state (its frames, record buffer and term pool)."""

    frames: NDArray[np.float64]
    act: NDArray[np.int64]
    cnt: NDArray[np.int64]
    outc: NDArray[np.float64]
    ccol: NDArray[np.int64]
    cinfo: NDArray[np.float64]
    hist: NDArray[np.int64]
    rec: NDArray[np.float64]
    pool: NDArray[np.int64]
    nrec: NDArray[np.int64] = field(default_factory=lambda: np.zeros(2, dtype=np.int64))
    ints: NDArray[np.int64] = field(default_factory=lambda: np.zeros(5, dtype=np.int64))
    best: NDArray[np.float64] = field(default_factory=lambda: np.zeros(14))
    poolid: NDArray[np.int64] = field(default_factory=lambda: np.full(1, -1, dtype=np.int64))

    def grow(self) -> None:
        """Double the record buffer or the pool, whichever is the fuller."""
        n, p = int(self.nrec[0]), int(self.nrec[1])
        if n >= self.rec.shape[0] // 2:
            rec = np.empty((2 * self.rec.shape[0], self.rec.shape[1]))
            rec[:n] = self.rec[:n]
            self.rec = rec
        if p + self.act.shape[1] > self.pool.shape[0] // 2:
            pool = np.empty((2 * self.pool.shape[0] + self.act.shape[1], 2), dtype=np.int64)
            pool[:p] = self.pool[:p]
            self.pool = pool


class _Pool:
    """The frontier's term lists (rows: term, colour class), appended to and never moved:
    a cell searched again leaves its list behind (a stage appends only its new cells')."""

    def __init__(self, first: NDArray[np.int64]) -> None:
        self.buf = np.empty((max(2 * first.shape[0], 1024), 2), dtype=np.int64)
        self.n = 0
        self.live = 0  # rows after the last compaction
        self.append(first)

    def append(self, rows: NDArray[np.int64]) -> int:
        """Append ``rows``; returns where they start."""
        need = self.n + rows.shape[0]
        if need > self.buf.shape[0]:
            buf = np.empty((max(2 * self.buf.shape[0], need), 2), dtype=np.int64)
            buf[:self.n] = self.buf[:self.n]
            self.buf = buf
        start = self.n
        self.buf[start:need] = rows
        self.n = need
        return start

    @property
    def rows(self) -> NDArray[np.int64]:
        return self.buf[:self.n]

    def compact(self, rec: NDArray[np.float64]) -> None:
        """Keep only the lists the cells ``rec`` refer to (each once); their offsets in
        ``rec`` are updated in place."""
        from solvers.certify._pose_kernels import _PLEN, _POFF

        offs, lens = rec[:, _POFF].astype(np.int64), rec[:, _PLEN].astype(np.int64)
        uo, first, inv = np.unique(offs, return_index=True, return_inverse=True)
        ul = lens[first]
        newoff = np.concatenate([[0], np.cumsum(ul)[:-1]]).astype(np.int64)
        idx = np.repeat(uo - newoff, ul) + np.arange(int(ul.sum()), dtype=np.int64)
        rows = self.buf[idx]
        self.buf = np.empty((max(2 * rows.shape[0], 1024), 2), dtype=np.int64)
        self.buf[:rows.shape[0]] = rows
        self.n = self.live = rows.shape[0]
        rec[:, _POFF] = newoff[inv]


def _merge(kept: NDArray[np.float64], parts: list[tuple[NDArray[np.float64], NDArray[np.int64]]],
           pool: _Pool) -> NDArray[np.float64]:
    """The frontier of cells ``kept`` (their lists in ``pool`` already) and of each (records,
    their lists) part (appended to ``pool``), sorted by bound."""
    from solvers.certify._pose_kernels import _BOUND, _POFF

    recs = [kept]
    for rec, rows in parts:
        if rec.shape[0] == 0:
            continue
        r = rec.copy()
        r[:, _POFF] += pool.append(rows)
        recs.append(r)
    rec = np.concatenate(recs)
    rec = np.ascontiguousarray(rec[np.argsort(rec[:, _BOUND], kind="stable")])
    if pool.n > max(COMPACT_ROWS, 2 * pool.live):
        pool.compact(rec)  # most lists are of cells searched since: dead
    return rec


class Frontier:
    """The anytime branch and bound over poses for one candidate (see the module docstring).

    Parameters
    ----------
    problem : WeightedTLSProblem
        The problem (normalised weights).
    R : (3, 3) ndarray
    t : (3,) ndarray
        The candidate pose: the upper bound, the frame's centre and the core's threshold.
    setup : callable
        ``setup(cap)``: the compiled search's inputs for the core against ``cap``, None when
        no consistent set can go below it, a string when the core is too large (as
        :func:`solvers.certify.pose_bnb.frontier` builds them).
    leaf_terms, leaf_nodes : int
        Cells with at most ``leaf_terms`` undecided terms are solved exactly, within
        ``leaf_nodes`` nodes.
    max_depth : int
        Frames of a worker's depth-first search.
    refine : callable, optional
        ``refine(problem, R, t) -> (R, t)`` for a better pose the search finds.
    workers : int
        Threads searching the frontier's cells.
    cap : float, optional
        Cells whose bound is at least this are dropped from the frontier (default: the best
        known cost, which no stage's threshold exceeds). A larger cap keeps them, so that
        :attr:`lower` may exceed the best known cost (for testing the bounds).
    """

    def __init__(self, problem: WeightedTLSProblem, R: NDArray[np.float64],
                 t: NDArray[np.float64], setup: Callable[[float], Any], *, leaf_terms: int,
                 leaf_nodes: int, max_depth: int, refine: Refine | None = None,
                 workers: int = 2, cap: float | None = None) -> None:
        self.problem, self.refine, self.workers = problem, refine, max(int(workers), 1)
        self.leaf_terms, self.leaf_nodes, self.max_depth = leaf_terms, leaf_nodes, max_depth
        self.u = float(problem.cost(R, t))
        self.c_out = _outlier_cost(problem, R, t)
        self.found: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        self.cap = self.u if cap is None else max(float(cap), self.u)
        self.cap_used = self.cap  # the least cap a cell was dropped at
        self.cells = 0
        self.hist = np.zeros((max_depth, 6), dtype=np.int64)
        self.failed = False
        self.t0 = time.perf_counter()
        self.merge_time = 0.0  # seconds the last pass took to merge its cells
        self.curve: list[tuple[float, float]] = []
        self._lock = threading.Lock()
        setup = setup(self.cap)
        self.empty = setup is None  # no consistent set can go below the cap
        self.too_large = isinstance(setup, str)
        self.roots = np.empty((0, 15))
        self.pool = _Pool(np.empty((0, 2), dtype=np.int64))
        if self.empty or self.too_large:
            return
        self.args, self.unit, self.cs, self.ct, self.allowance, st = setup
        m = st.act.shape[1] if st.cnt[0] > 0 else 0
        self.m = int(st.cnt[0])
        self.base0 = float(st.outc[0])
        self.roots = np.array([[0.0, 0.0, 0.0, np.pi, 0.0, 0.0, 0.0, st.frames[0, 7], -np.inf,
                                0.0, float(self.m), self.base0, *st.cinfo[0]]])
        self.pool = _Pool(np.stack([np.arange(max(m, 1), dtype=np.int64),
                                    st.ccol[0, :max(m, 1)]], axis=1))

    @property
    def lower(self) -> float:
        """The least bound of the frontier's cells: no pose costs less (at most the least cap
        a cell was dropped at)."""
        if self.empty:
            return self.cap
        if self.too_large or self.failed:
            return -np.inf
        least = float(self.roots[0, 8]) if self.roots.shape[0] else np.inf
        return min(least, self.cap_used)

    def _worker(self) -> _Worker:
        from solvers.certify._pose_kernels import FRAME_COLS, REC_COLS

        MAX_DEPTH = self.max_depth  # noqa: N806
        m = max(self.m, 1)
        ccol = np.zeros((MAX_DEPTH, m), dtype=np.int64)
        return _Worker(np.zeros((MAX_DEPTH, FRAME_COLS)),
                       np.zeros((MAX_DEPTH, m), dtype=np.int64),
                       np.zeros(MAX_DEPTH, dtype=np.int64), np.zeros(MAX_DEPTH), ccol,
                       np.zeros((MAX_DEPTH, 3)), np.zeros((MAX_DEPTH, 6), dtype=np.int64),
                       np.empty((FIRST_ROWS, REC_COLS)),
                       np.empty((FIRST_ROWS * 8, 2), dtype=np.int64),
                       poolid=np.full(MAX_DEPTH, -1, dtype=np.int64))

    def threshold(self, gap: float) -> float:
        """The threshold of ``gap`` against the best pose known."""
        return stage_threshold(self.u, self.c_out, gap)

    def run(self, gap: float, deadline: float, *, max_cells: int | None = None) -> bool:
        """Raise the frontier's bounds to the threshold of ``gap`` (against the best pose known,
        which may improve meanwhile) until ``deadline`` (``time.perf_counter()``) or until
        ``max_cells`` cells have been visited in all; returns whether it got there."""
        if self.empty:
            return True
        if self.too_large or self.failed:
            return False
        while not self.failed and self.lower < self.threshold(gap) - self.allowance:
            if time.perf_counter() >= deadline or (max_cells is not None
                                                   and self.cells >= max_cells):
                return False
            self._pass(gap, deadline, max_cells)
            self.curve.append((time.perf_counter() - self.t0, self.lower))
        return not self.failed

    def _pass(self, gap: float, deadline: float, max_cells: int | None) -> None:
        """Search below every cell of the frontier whose bound is below the threshold of
        ``gap`` (to at most ``SPLIT_DEPTH`` levels)."""
        state = {"next": 0, "stop": False, "carried": []}
        roots, rpool = self.roots, self.pool.rows
        # The searching stops early enough for the merge of its cells to end by the deadline
        # (about as long as the last one, with a little more to merge).
        deadline -= 1.5 * self.merge_time
        block = max(1, min(64, roots.shape[0] // (8 * self.workers)))
        kern = compiled("solvers.certify._pose_kernels").pose_frontier

        def work() -> list[tuple[NDArray[np.float64], NDArray[np.int64]]]:
            w = self._worker()
            out = []
            while True:
                with self._lock:
                    r0 = state["next"]
                    thr = self.threshold(gap)
                    if (state["stop"] or r0 >= roots.shape[0] or roots[r0, 8] >= thr
                            or time.perf_counter() >= deadline):
                        break
                    r1 = min(roots.shape[0], r0 + block)
                    state["next"] = r1
                self._block(kern, w, roots[r0:r1], rpool, gap, deadline, max_cells, state)
                out.append((w.rec[:w.nrec[0]].copy(), w.pool[:w.nrec[1]].copy()))
                w.nrec[:] = 0
            with self._lock:
                self.hist += w.hist
            return out

        if self.workers == 1:
            parts = work()
        else:
            with ThreadPoolExecutor(self.workers) as ex:
                futures = [ex.submit(work) for _ in range(self.workers)]
                parts = [p for f in futures for p in f.result()]
        started = time.perf_counter()
        kept = np.concatenate(state["carried"] + [roots[state["next"]:]])
        self.roots = _merge(kept, parts, self.pool)
        self.merge_time = time.perf_counter() - started

    def _block(self, kern, w: _Worker, roots: NDArray[np.float64],  # noqa: ANN001
               rpool: NDArray[np.int64], gap: float, deadline: float, max_cells: int | None,
               state: dict) -> None:
        """Search below ``roots`` (a block of the frontier) with worker ``w``; on a deadline or a
        failure the block's roots not finished are carried over as they are."""
        a = self.args
        w.ints[:] = 0
        while True:
            with self._lock:
                thr = self.threshold(gap)
                cap = min(self.cap, max(self.u, thr))
                self.cap_used = min(self.cap_used, cap)
            start = int(w.ints[1])
            chunk = CHUNK_NODES if max_cells is None else max(min(CHUNK_NODES,
                                                                  max_cells - self.cells), 1)
            code = kern(*a[:7], w.ccol, w.cinfo, a[9], a[10], float(thr), float(self.allowance),
                        self.leaf_terms, self.leaf_nodes, start + chunk, roots, rpool, self.base0,
                        w.frames, w.act, w.cnt, w.outc, w.ints, w.best, w.hist, w.rec, w.nrec,
                        w.pool, w.poolid, float(cap), SPLIT_DEPTH)
            with self._lock:
                self.cells += int(w.ints[1]) - start
                over = max_cells is not None and self.cells >= max_cells
            if code == 0:
                return
            if code == 4:
                w.grow()
                continue
            if code == 3:
                # Not better when another worker found a better pose meanwhile: the threshold
                # has come down, so the cell will not offer it again.
                if self._better(w.best) or self.threshold(gap) < thr:
                    continue
                code = 2
            if code == 2 or over or time.perf_counter() >= deadline:
                with self._lock:
                    state["stop"] = True
                    self.failed = self.failed or code == 2
                    state["carried"].append(roots[int(w.ints[3]):].copy())
                return

    def _better(self, best: NDArray[np.float64]) -> bool:
        """A better pose from the kernel's ``best`` (the least-squares pose of a cell's inlier
        set, centred frame), refined; whether it is better than the best known."""
        p = self.problem
        Rb = best[2:11].reshape(3, 3).copy()
        tb = best[11:14] * self.unit + self.ct - Rb @ self.cs
        if self.refine is not None:
            Rr, tr = self.refine(p, Rb, tb)
            if p.cost(Rr, tr) <= p.cost(Rb, tb):
                Rb, tb = Rr, tr
        with self._lock:
            cost = float(p.cost(Rb, tb))
            if not cost < self.u:
                return False
            self.u, self.c_out, self.found = cost, _outlier_cost(p, Rb, tb), (Rb, tb)
        return True


def stage_threshold(u: float, c_out: float, gap: float) -> float:
    """The threshold whose proof gives a gap of at most ``gap`` to a pose of cost ``u`` with
    outlier cost ``c_out``: ``undiluted_gap(u, thr, c_out) <= gap`` for ``thr <= u``."""
    return u - gap * (1.0 + abs(u - c_out))


def _outlier_cost(problem: WeightedTLSProblem, R: NDArray[np.float64],
                  t: NDArray[np.float64]) -> float:
    r2 = problem.residuals_sq(R, t)
    return float(problem.cbar2 * problem.weights[r2 >= problem.cbar2].sum())
