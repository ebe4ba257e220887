"""Robust registration front-end: GNC-TLS, with max-clique pruning when it pays."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from solvers.lie import make_transform
from solvers.problem import WeightedTLSProblem
from solvers.registration.pruning import prune_maximum_cliques, vote_translation
from solvers.result import RegistrationResult, SolverStatus

__all__ = [
    "GNCParams",
    "PruningParams",
    "solve_gnc",
    "solve_pruned",
    "solve_registration",
    "degeneracy",
]

log = logging.getLogger(__name__)

Method = Literal["auto", "gnc", "pruned"]


@dataclass(frozen=True)
class GNCParams:
    """Parameters of GNC-TLS.

    Attributes
    ----------
    max_iterations : int
        Outer iterations (one weighted Procrustes each).
    mu_factor : float
        Growth of the GNC control parameter ``mu`` per iteration (> 1).
    cost_tol : float
        Relative change of the surrogate cost below which GNC stops.
    """

    max_iterations: int = 100
    mu_factor: float = 1.4
    cost_tol: float = 1e-12

    def __post_init__(self) -> None:
        if self.max_iterations < 1:
            raise ValueError(f"`max_iterations` must be >= 1, got {self.max_iterations}.")
        if not self.mu_factor > 1:
            raise ValueError(f"`mu_factor` must be > 1, got {self.mu_factor}.")
        if not self.cost_tol >= 0:
            raise ValueError(f"`cost_tol` must be >= 0, got {self.cost_tol}.")


@dataclass(frozen=True)
class PruningParams:
    """When and how the front-end prunes with the pairwise-consistency max clique.

    Attributes
    ----------
    max_correspondences : int
        Above this many correspondences the dense O(N^2) graph (N^2 bytes) is not built
        and GNC runs alone.
    exact_clique_max_vertices : int or None
        Largest graph (after greedy bounding and core pruning) searched exactly for the maximum
        clique; beyond it the greedy clique is used and ``info["max_clique_exact"]`` is False.
        ``None`` always searches exactly (exponential time in the worst case).
    max_tied_cliques : int
        When several maximum cliques tie, up to this many are each solved and the pose of
        lowest TLS cost is kept (with few inliers, a tied clique can be mostly outliers).
    """

    max_correspondences: int = 5_000
    exact_clique_max_vertices: int | None = 500
    max_tied_cliques: int = 16

    def __post_init__(self) -> None:
        if self.max_correspondences < 3:
            raise ValueError(
                f"`max_correspondences` must be >= 3, got {self.max_correspondences}."
            )
        if self.max_tied_cliques < 1:
            raise ValueError(f"`max_tied_cliques` must be >= 1, got {self.max_tied_cliques}.")


def degeneracy(
    points: NDArray[np.float64], weights: NDArray[np.float64], noise_bound: float
) -> str | None:
    """Why ``points`` (with positive ``weights``) fail to fix a rotation, or ``None``.

    Coincident points leave rotation free; collinear points leave the rotation about their
    line free. Spread is judged against the noise bound, below which it is indistinguishable
    from noise.
    """
    from solvers.registration import _kernels

    ev, count = _kernels.weighted_spread(
        np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(weights, dtype=np.float64)
    )
    if count < 3:
        return f"only {count} inlier(s); at least 3 non-collinear points are needed"
    floor = max(noise_bound, 1e-12 * max(1.0, float(np.abs(points).max())))
    if ev[0] <= floor:
        return f"the inliers are coincident (spread {ev[0]:.3g} <= noise bound {floor:.3g})"
    if ev[1] <= floor:
        return (
            f"the inliers are collinear (spread across the line {ev[1]:.3g} <= noise bound "
            f"{floor:.3g}); the rotation about that line is undetermined"
        )
    return None


def _finish(
    problem: WeightedTLSProblem,
    R: NDArray[np.float64],
    t: NDArray[np.float64],
    *,
    iterations: int,
    t0: float,
    status: SolverStatus,
    message: str,
    solver: str,
    info: dict | None = None,
) -> RegistrationResult:
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        R, t = np.eye(3), np.zeros(3)
        status, message = SolverStatus.NUMERICAL_ERROR, "non-finite pose estimate"
    r2 = problem.residuals_sq(R, t)
    inliers = r2 <= problem.cbar2
    if status is SolverStatus.CONVERGED:
        why = degeneracy(problem.source, problem.weights * inliers, float(problem.noise_bound.min()))
        if why is not None:
            status, message = SolverStatus.DEGENERATE, f"degenerate geometry: {why}"
            if inliers.sum() < 3:
                status = SolverStatus.INSUFFICIENT_INLIERS
    return RegistrationResult(
        T_target_source=make_transform(R, t),
        inliers=inliers,
        cost=problem.cost_from_residuals(r2),
        iterations=int(iterations),
        solve_time=time.perf_counter() - t0,
        status=status,
        message=message,
        solver=solver,
        info=info or {},
    )


def _gnc_core(
    problem: WeightedTLSProblem, idx: NDArray[np.int64] | None, params: GNCParams
) -> tuple[NDArray[np.float64], NDArray[np.float64], int, bool, bool]:
    a, b = problem.source, problem.target
    w, beta = problem.weights, problem.noise_bound
    if idx is not None:
        a, b, w, beta = a[idx], b[idx], w[idx], beta[idx]
    from solvers.registration import _kernels  # numba: imported on first solve

    R, t, _gw, it, converged, ok = _kernels.gnc_tls(
        np.ascontiguousarray(a),
        np.ascontiguousarray(b),
        np.ascontiguousarray(w),
        np.ascontiguousarray(1.0 / beta**2),
        problem.cbar2,
        params.max_iterations,
        params.mu_factor,
        params.cost_tol,
    )
    return R, t, int(it), bool(converged), bool(ok)


def solve_gnc(
    problem: WeightedTLSProblem, *, params: GNCParams | None = None
) -> RegistrationResult:
    """Solve a weighted TLS problem with GNC-TLS (Yang, Antonante, Tzoumas, Carlone 2020).

    Robust to roughly 70-80% outliers; use :func:`solve_pruned` beyond.
    """
    params = params or GNCParams()
    t0 = time.perf_counter()
    R, t, it, converged, ok = _gnc_core(problem, None, params)
    if not ok:
        return _finish(problem, np.eye(3), np.zeros(3), iterations=it, t0=t0,
                       status=SolverStatus.INSUFFICIENT_INLIERS,
                       message="all weights vanished: no correspondence left to fit",
                       solver="gnc")
    status = SolverStatus.CONVERGED if converged else SolverStatus.MAX_ITERATIONS
    msg = (f"GNC converged in {it} iterations" if converged
           else f"GNC stopped at the iteration limit ({params.max_iterations})")
    return _finish(problem, R, t, iterations=it, t0=t0, status=status, message=msg, solver="gnc")


def solve_pruned(
    problem: WeightedTLSProblem,
    *,
    params: GNCParams | None = None,
    pruning: PruningParams | None = None,
) -> RegistrationResult:
    """Max-clique pruning, GNC on the survivors and exact per-axis translation voting.

    The consistency graph ignores weights; correspondences of zero weight are left out of it.
    """
    params = params or GNCParams()
    pruning = pruning or PruningParams()
    t0 = time.perf_counter()
    active = np.flatnonzero(problem.weights > 0)
    if active.size < 3:
        return _finish(problem, np.eye(3), np.zeros(3), iterations=0, t0=t0,
                       status=SolverStatus.INSUFFICIENT_INLIERS,
                       message=f"only {active.size} correspondence(s) have positive weight",
                       solver="pruned")
    cliques, n_edges, exact = prune_maximum_cliques(
        problem.source[active], problem.target[active], problem.noise_bound[active],
        problem.cbar2, limit=pruning.max_tied_cliques,
        exact_max_vertices=pruning.exact_clique_max_vertices,
    )
    size = int(cliques[0].size)
    info = {"max_clique_size": size, "graph_edges": int(n_edges),
            "max_clique_exact": exact, "tied_max_cliques": len(cliques)}
    if size < 3:
        return _finish(problem, np.eye(3), np.zeros(3), iterations=0, t0=t0,
                       status=SolverStatus.INSUFFICIENT_INLIERS,
                       message=f"the largest consistent set has {size} correspondence(s)",
                       solver="pruned", info=info)
    # Tied maximum cliques (likely with few inliers): solve each, keep the lowest TLS cost.
    best: tuple[float, NDArray[np.float64], NDArray[np.float64], int, bool] | None = None
    for clique in cliques:
        survivors = active[clique]
        R, t, it, converged, ok = _gnc_core(problem, survivors, params)
        if not ok:
            continue
        t_vote = vote_translation(problem, R, survivors)
        cost, cost_vote = problem.cost(R, t), problem.cost(R, t_vote)
        if cost_vote < cost:  # keep whichever translation the full TLS cost prefers
            t, cost = t_vote, cost_vote
        if best is None or cost < best[0]:
            best = (cost, R, t, it, converged)
    if best is None:
        return _finish(problem, np.eye(3), np.zeros(3), iterations=0, t0=t0,
                       status=SolverStatus.NUMERICAL_ERROR, message="GNC on the survivors failed",
                       solver="pruned", info=info)
    _, R, t, it, converged = best
    status = SolverStatus.CONVERGED if converged else SolverStatus.MAX_ITERATIONS
    tied = f" (best of {len(cliques)} tied)" if len(cliques) > 1 else ""
    msg = (f"max clique kept {size}/{problem.n}{tied}; GNC converged in {it} iterations"
           if converged else f"GNC on the survivors hit the iteration limit ({params.max_iterations})")
    return _finish(problem, R, t, iterations=it, t0=t0, status=status, message=msg,
                   solver="pruned", info=info)


def solve_registration(
    problem: WeightedTLSProblem,
    *,
    method: Method = "auto",
    gnc: GNCParams | None = None,
    pruning: PruningParams | None = None,
) -> RegistrationResult:
    """Solve a weighted TLS problem, choosing pruning automatically.

    ``method="auto"`` prunes whenever the O(N^2) consistency graph is affordable
    (``N <= pruning.max_correspondences``): pruning costs little next to GNC and is what keeps
    the estimate right past 80% outliers. Otherwise GNC runs alone. The max clique ignores
    weights, so with uneven weights (or when pruning fails) GNC on all correspondences runs too
    and the pose of lower TLS cost is returned; ``solve_time`` covers both.
    """
    pruning = pruning or PruningParams()
    if method not in ("auto", "gnc", "pruned"):
        raise ValueError(f"`method` must be 'auto', 'gnc' or 'pruned', got {method!r}.")
    if method == "gnc" or (method == "auto" and problem.n > pruning.max_correspondences):
        return solve_gnc(problem, params=gnc)
    result = solve_pruned(problem, params=gnc, pruning=pruning)
    if method != "auto":
        return result
    w = problem.weights
    uneven = bool(np.ptp(w[w > 0]) > 1e-12 * w.max()) if np.any(w > 0) else False
    if result.success and not uneven:
        return result
    if not result.success and result.status is SolverStatus.DEGENERATE:
        return result
    # The max clique ignores weights (and may fail): GNC on everything sees them; keep the
    # pose with the lower TLS cost.
    fallback = solve_gnc(problem, params=gnc)
    if fallback.success and (not result.success or fallback.cost < result.cost):
        log.info("GNC on all correspondences beat the pruned solve (cost %.6g vs %.6g)",
                 fallback.cost, result.cost)
        info = dict(fallback.info, pruned_cost=result.cost, pruned_status=result.status.value)
        return replace(fallback, info=info,
                       solve_time=result.solve_time + fallback.solve_time)
    return replace(result, solve_time=result.solve_time + fallback.solve_time)
