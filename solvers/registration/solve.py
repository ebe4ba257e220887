"""Robust registration front-end: GNC-TLS, with max-clique pruning when it pays."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.jit import compiled
from solvers.problem import WeightedTLSProblem
from solvers.registration.pruning import _prune_rows, _vote_rows
from solvers.result import RegistrationResult, SolverStatus
from solvers.validation import _check_correspondences, check_count

__all__ = [
    "LARGE_CORE_KERNELS",
    "PRUNED_SOLVE_KERNELS",
    "GNCParams",
    "PruningParams",
    "solve_gnc",
    "solve_pruned",
    "solve_registration",
    "degeneracy",
    "to_unit_scale",
    "from_unit_scale",
    "check_graph_memory",
    "check_problem",
    "judge_pose",
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
        check_count(self.max_iterations, "max_iterations", minimum=1)
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
        ``None`` (default): any size; ``clique_max_work`` bounds the search's time.
    max_tied_cliques : int
        When several maximum cliques tie, up to this many are each solved and the pose of
        lowest TLS cost is kept (with few inliers, a tied clique can be mostly outliers).
    clique_max_work : int or None
        Budget of the exact clique search in adjacency look-ups (about 5 ns each; the MCQ
        search for ties gets a quarter more, the bitset search for large cores counts
        :data:`solvers.registration.pruning.BITSET_WORDS_PER_LOOKUP` word operations per
        look-up, ties included): bounds its time on dense graphs. When it runs out, the
        largest clique found is kept and ``info["max_clique_exact"]`` is False. ``None``:
        unbounded.
    """

    max_correspondences: int = 5_000
    exact_clique_max_vertices: int | None = None
    max_tied_cliques: int = 16
    clique_max_work: int | None = 10_000_000

    def __post_init__(self) -> None:
        check_count(self.max_correspondences, "max_correspondences", minimum=3)
        if self.exact_clique_max_vertices is not None:
            check_count(self.exact_clique_max_vertices, "exact_clique_max_vertices", minimum=0)
        check_count(self.max_tied_cliques, "max_tied_cliques", minimum=1)
        if self.clique_max_work is not None:
            check_count(self.clique_max_work, "clique_max_work", minimum=1)


_DEFAULT_GNC = GNCParams()
_DEFAULT_PRUNING = PruningParams()  # frozen: shared, not rebuilt (and re-validated) per solve

PRUNED_SOLVE_KERNELS = tuple(f"solvers.registration._kernels:{name}" for name in (
    "gnc_tls", "weighted_spread", "multistart_greedy_clique", "k_core", "scalar_tls_rows",
    "consistency_matrix", "row_degrees"))
"""The compiled kernels every pruned solve calls, longest compilation first (for
:func:`solvers.jit.warm_up`: its helper takes them from the front, the command from the back);
the exact clique search (``max_clique_bnb``) runs only when the peeled graph is not a clique."""

LARGE_CORE_KERNELS = ("solvers.registration._clique_kernels:max_clique_bitset",)
"""The exact clique search of cores over a few hundred vertices (dense graphs of real features,
e.g. eq. (2) problems), for :func:`solvers.jit.warm_up`."""


def degeneracy(
    points: NDArray[np.float64], weights: NDArray[np.float64], noise_bound: float
) -> str | None:
    """Why ``points`` (with positive ``weights``) fail to fix a rotation, or ``None``.

    Coincident points leave rotation free; collinear points leave the rotation about their
    line free. Spread is judged against the noise bound, below which it is indistinguishable
    from noise.
    """
    _kernels = compiled("solvers.registration._kernels")  # a 3x3 eigenproblem

    arr = _kernels.as_kernel_array
    # Spread judged in units of the points' extent, so any scale works (1e-200 .. 1e200).
    count, scale, ev = _kernels.weighted_spread(arr(points), arr(weights))
    ev0, ev1 = float(ev[0]), float(ev[1])
    if count < 3:
        return f"only {count} inlier(s); at least 3 non-collinear points are needed"
    if not scale > 0:
        return "the inliers are coincident (all at the origin)"
    # Below ~1e-12 of the extent, spread is floating-point rounding, not geometry.
    floor = max(noise_bound, 1e-12 * scale)
    # Ratios, not lengths: the problem may have been rescaled to unit size.
    if ev0 <= floor:
        return (f"the inliers are coincident (their spread is {ev0 / floor:.3g} times the noise "
                "bound; is the noise bound far larger than the points' extent?)")
    if ev1 <= floor:
        return (
            f"the inliers are collinear (their spread across the line is {ev1 / floor:.3g} "
            "times the noise bound); the rotation about that line is undetermined"
        )
    return None


def judge_pose(
    problem: WeightedTLSProblem, inliers: NDArray[np.bool_], message: str
) -> tuple[SolverStatus, str]:
    """Status and message of a pose whose solver converged, from its ``inliers`` (N,):
    ``CONVERGED`` with ``message``, or why the inliers do not fix a pose."""
    src, _, _, w = problem._kernel_arrays
    why = degeneracy(src, w * inliers, problem._min_noise_bound)
    if why is None:
        return SolverStatus.CONVERGED, message
    if np.count_nonzero(inliers & (w > 0)) < 3:
        return SolverStatus.INSUFFICIENT_INLIERS, f"degenerate geometry: {why}"
    return SolverStatus.DEGENERATE, f"degenerate geometry: {why}"


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
    r2: NDArray[np.float64] | None = None,
    cost: float | None = None,
) -> RegistrationResult:
    """The result of the pose ``(R, t)``; ``r2`` and ``cost``: its residuals and TLS cost when
    already computed."""
    T = np.empty((4, 4))
    T[:3, :3] = R
    T[:3, 3] = t
    T[3] = (0.0, 0.0, 0.0, 1.0)
    if not math.isfinite(T.sum()):  # NaN/inf propagate into the sum (|R|, |t| ~ 1: no overflow)
        T, r2 = np.eye(4), None
        status, message = SolverStatus.NUMERICAL_ERROR, "non-finite pose estimate"
    if r2 is None:
        r2, cost = problem.residuals_sq(T[:3, :3], T[:3, 3]), None
    if cost is None:
        cost = problem.cost_from_residuals(r2)
    inliers = r2 <= problem.cbar2
    if status is SolverStatus.CONVERGED:
        status, message = judge_pose(problem, inliers, message)
    return RegistrationResult._fresh(
        T_target_source=T,
        inliers=inliers,
        cost=cost,
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
    a, b, _, w = problem._kernel_arrays  # writable: no copies for the kernel
    inv_beta2 = problem._inv_beta2
    if idx is not None:
        a, b, w, inv_beta2 = a[idx], b[idx], w[idx], inv_beta2[idx]
    _kernels = compiled("solvers.registration._kernels")  # numba: imported on first solve

    R, t, _gw, it, converged, ok = _kernels.gnc_tls(
        a,
        b,
        w,
        inv_beta2,
        problem.cbar2,
        params.max_iterations,
        params.mu_factor,
        params.cost_tol,
    )
    return R, t, int(it), bool(converged), bool(ok)


def _solve_gnc(
    problem: WeightedTLSProblem, *, params: GNCParams | None = None
) -> RegistrationResult:
    """See :func:`solve_gnc` (on a unit-scale problem)."""
    params = params or _DEFAULT_GNC
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


def _solve_pruned(
    problem: WeightedTLSProblem,
    *,
    params: GNCParams | None = None,
    pruning: PruningParams | None = None,
) -> RegistrationResult:
    """See :func:`solve_pruned` (on a unit-scale problem)."""
    params = params or _DEFAULT_GNC
    pruning = pruning or _DEFAULT_PRUNING
    t0 = time.perf_counter()
    # Uniform positive weights (the usual case): every correspondence is active.
    active = (np.arange(problem.n) if problem._uniform_weights
              else np.flatnonzero(problem.weights > 0))
    if active.size < 3:
        return _finish(problem, np.eye(3), np.zeros(3), iterations=0, t0=t0,
                       status=SolverStatus.INSUFFICIENT_INLIERS,
                       message=f"only {active.size} correspondence(s) have positive weight",
                       solver="pruned")
    check_graph_memory(int(active.size))
    at, bt = problem._points_t
    _, _, beta, w = problem._kernel_arrays
    every = active.size == problem.n  # the usual case: no copies of the data
    # Column selection of a (3, N) array comes out Fortran-ordered: the kernels take C order.
    cliques, n_edges, exact = _prune_rows(
        at if every else np.ascontiguousarray(at[:, active]),
        bt if every else np.ascontiguousarray(bt[:, active]),
        beta if every else beta[active],
        problem.cbar2, limit=pruning.max_tied_cliques,
        exact_max_vertices=pruning.exact_clique_max_vertices, max_work=pruning.clique_max_work,
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
    best: tuple[float, NDArray[np.float64], NDArray[np.float64], int, bool, NDArray[np.float64]] | None = None
    cbar2 = problem.cbar2
    for clique in cliques:
        survivors = active[clique]
        # Every correspondence survived (no outliers): no gathered copies.
        sel = None if survivors.size == problem.n else survivors
        R, t, it, converged, ok = _gnc_core(problem, sel, params)
        if not ok:
            continue
        # The rotated points, once, for the vote and for both translations' residuals.
        moved = bt - R @ at  # (3, N): b_k - R a_k
        uniform = problem._uniform_noise
        if sel is None:
            t_vote = _vote_rows(moved, beta, w, cbar2, uniform=uniform)
        else:
            # take: C-contiguous (moved[:, sel] is laid out in Fortran order)
            t_vote = _vote_rows(moved.take(sel, axis=1), beta[sel], w[sel], cbar2,
                                uniform=uniform)
        r2, r2_vote, cost, cost_vote = problem._residuals_sq_pair_t(moved, t, t_vote)
        if cost_vote < cost:  # keep whichever translation the full TLS cost prefers
            t, cost, r2 = t_vote, cost_vote, r2_vote
        if best is None or cost < best[0]:
            best = (cost, R, t, it, converged, r2)
    if best is None:
        return _finish(problem, np.eye(3), np.zeros(3), iterations=0, t0=t0,
                       status=SolverStatus.NUMERICAL_ERROR, message="GNC on the survivors failed",
                       solver="pruned", info=info)
    _, R, t, it, converged, r2 = best
    status = SolverStatus.CONVERGED if converged else SolverStatus.MAX_ITERATIONS
    tied = f" (best of {len(cliques)} tied)" if len(cliques) > 1 else ""
    msg = (f"max clique kept {size}/{problem.n}{tied}; GNC converged in {it} iterations"
           if converged else f"GNC on the survivors hit the iteration limit ({params.max_iterations})")
    return _finish(problem, R, t, iterations=it, t0=t0, status=status, message=msg,
                   solver="pruned", info=info, r2=r2, cost=best[0])


def _solve_registration(
    problem: WeightedTLSProblem,
    *,
    method: Method = "auto",
    gnc: GNCParams | None = None,
    pruning: PruningParams | None = None,
) -> RegistrationResult:
    """See :func:`solve_registration` (on a unit-scale problem)."""
    pruning = pruning or _DEFAULT_PRUNING
    if method not in ("auto", "gnc", "pruned"):
        raise ValueError(f"`method` must be 'auto', 'gnc' or 'pruned', got {method!r}.")
    if method == "gnc" or (method == "auto" and problem.n > pruning.max_correspondences):
        return _solve_gnc(problem, params=gnc)
    result = _solve_pruned(problem, params=gnc, pruning=pruning)
    if method != "auto":
        return result
    w = problem.weights
    wmin, wmax = (1.0, 1.0) if problem._uniform_weights else (float(w.min()), float(w.max()))
    if wmin > 0.0:  # the usual case
        uneven = wmax - wmin > 1e-12 * wmax
    else:
        uneven = bool(np.ptp(w[w > 0]) > 1e-12 * wmax) if wmax > 0.0 else False
    if result.success and not uneven:
        return result
    if not result.success and result.status is SolverStatus.DEGENERATE:
        return result
    # The max clique ignores weights (and may fail): GNC on everything sees them; keep the
    # pose with the lower TLS cost.
    fallback = _solve_gnc(problem, params=gnc)
    if fallback.success and (not result.success or fallback.cost < result.cost):
        log.info("GNC on all correspondences beat the pruned solve (cost %.6g vs %.6g)",
                 fallback.cost, result.cost)
        info = dict(fallback.info, pruned_cost=result.cost, pruned_status=result.status.value)
        return replace(fallback, info=info,
                       solve_time=result.solve_time + fallback.solve_time)
    return replace(result, solve_time=result.solve_time + fallback.solve_time)


# Noise bounds below this fraction of the points' extent are far below float64 resolution
# (1e-16): no residual but an exact zero can meet them, and the same holds at this floor, which
# keeps 1 / beta^2 finite inside the kernels.
_MIN_RELATIVE_NOISE_BOUND = 1e-100


def to_unit_scale(problem: WeightedTLSProblem) -> tuple[WeightedTLSProblem, float]:
    """The problem scaled so that its largest coordinate is about 1, and the scale.

    Residuals, inliers and the TLS cost are invariant under a common scaling of the points,
    the noise bound and the translation; the scale is a power of two, so the scaling is exact.
    """
    if problem.__dict__.get("_at_unit_scale"):
        return problem, 1.0  # made by this function or unit_scale_problem
    src, dst, beta, w = problem._kernel_arrays
    extent = max(float(src.max()), -float(src.min()), float(dst.max()), -float(dst.min()))
    scale = math.ldexp(1.0, math.frexp(extent)[1]) if extent > 0 else 1.0
    if scale == 1.0 and float(beta.min()) >= _MIN_RELATIVE_NOISE_BOUND:
        return problem, 1.0  # already at unit scale (e.g. the second call of a solve)
    beta = np.maximum(beta / scale, _MIN_RELATIVE_NOISE_BOUND)
    # Division by a power of two is exact (and keeps the data valid): no second validation.
    unit = WeightedTLSProblem._from_checked(src / scale, dst / scale, beta, w, problem.cbar2)
    for key in ("_uniform_weights", "_uniform_noise"):  # cached properties already known
        if key in problem.__dict__:
            unit.__dict__[key] = problem.__dict__[key]
    unit.__dict__["_at_unit_scale"] = True
    return unit, scale


def unit_scale_problem(
    source: ArrayLike,
    target: ArrayLike,
    *,
    noise_bound: ArrayLike,
    weights: ArrayLike | None = None,
    cbar2: float = 1.0,
) -> tuple[WeightedTLSProblem, float]:
    """``to_unit_scale(WeightedTLSProblem(source, target, ...))`` in one pass.

    Validates like :class:`~solvers.problem.WeightedTLSProblem` and scales the validated copies
    in place (one problem, no second set of arrays: a small solve's overhead).
    """
    src, dst, beta, w, c2, extent = _check_correspondences(
        source, target, noise_bound, weights, cbar2, 3)
    scale = math.ldexp(1.0, math.frexp(extent)[1]) if extent > 0 else 1.0
    inv = 1.0 / scale  # a power of two: multiplying by it is the exact division
    if scale != 1.0:
        src *= inv
        dst *= inv
        beta *= inv
    beta_min = noise_bound if type(noise_bound) is float else float(beta.min())
    if beta_min * inv < _MIN_RELATIVE_NOISE_BOUND:
        np.maximum(beta, _MIN_RELATIVE_NOISE_BOUND, out=beta)
    unit = WeightedTLSProblem._from_checked(src, dst, beta, w, c2)
    if type(noise_bound) is float:
        unit.__dict__["_uniform_noise"] = True
    if weights is None:
        unit.__dict__["_uniform_weights"] = True  # all ones
    unit.__dict__["_at_unit_scale"] = True
    return unit, scale


def from_unit_scale(result: RegistrationResult, scale: float) -> RegistrationResult:
    """A result on :func:`to_unit_scale`'s problem, with its translation back in the original units.

    Inliers, cost and certificate bounds are scale-invariant and carry over unchanged; the poses
    recorded in ``info`` (keys ending in ``T_target_source``, also one dictionary deep, e.g. a
    replaced candidate's) are scaled back like the result's own.
    """
    if scale == 1.0:
        return result
    T = np.array(result.T_target_source)
    T[:3, 3] *= scale
    out = result._with_transform(T)
    info = _info_from_unit_scale(result.info, scale)
    if info is not result.info:
        object.__setattr__(out, "info", info)
    return out


def _info_from_unit_scale(info: dict[str, Any], scale: float, depth: int = 0) -> dict[str, Any]:
    """``info`` with its recorded poses' translations multiplied by ``scale`` (a new dict when
    any is; the lists stay lists)."""
    new: dict[str, Any] = {}
    changed = False
    for key, value in info.items():
        if isinstance(key, str) and key.endswith("T_target_source") and value is not None:
            T = np.array(value, dtype=np.float64)
            if T.shape == (4, 4):
                T[:3, 3] *= scale
                value = T.tolist() if isinstance(value, list) else T
                changed = True
        elif isinstance(value, dict) and depth == 0:
            sub = _info_from_unit_scale(value, scale, depth + 1)
            changed |= sub is not value
            value = sub
        new[key] = value
    return new if changed else info


_ALWAYS_AFFORDABLE = 1 << 24
"""Graphs up to 16 MiB (N = 4096) are not checked against the available memory."""


def check_graph_memory(n: int) -> None:
    """Refuse, before allocating, a consistency graph of ``n`` vertices that memory cannot hold.

    The dense graph takes ``n^2`` bytes; more than half of the available memory is refused.

    Raises
    ------
    MemoryError
        With ``n`` and the bytes needed.
    """
    need = n * n
    if need <= _ALWAYS_AFFORDABLE:
        return  # spares small solves the system call
    available = _available_memory()
    if available is not None and need > available // 2:
        raise MemoryError(
            f"max-clique pruning of N = {n} correspondences needs a dense {n} x {n} consistency "
            f"graph ({need / 1e9:.3g} GB) but only {available / 1e9:.3g} GB of memory is "
            "available; use prune='auto' or 'never' (GNC without pruning), or fewer "
            "correspondences."
        )


def _available_memory() -> int | None:
    import os

    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # not POSIX: do not guess
        return None


def check_problem(problem: object) -> WeightedTLSProblem:
    """``problem`` if it is a :class:`~solvers.problem.WeightedTLSProblem`, else a ``TypeError``
    saying how to make one."""
    if not isinstance(problem, WeightedTLSProblem):
        raise TypeError(
            f"Expected `problem` to be a WeightedTLSProblem, got {type(problem).__name__}; build "
            "one with WeightedTLSProblem(source, target, noise_bound=...) or call "
            "certpose.register(source, target, noise_bound=...).")
    return problem


def solve_gnc(
    problem: WeightedTLSProblem, *, params: GNCParams | None = None
) -> RegistrationResult:
    """Solve a weighted TLS problem with GNC-TLS (Yang, Antonante, Tzoumas, Carlone 2020).

    Robust to roughly 70-80% outliers; use :func:`solve_pruned` beyond. The problem is scaled
    to unit size first, so any finite scale of the points and noise bound is solved alike.
    """
    check_problem(problem)
    unit, scale = to_unit_scale(problem)
    return from_unit_scale(_solve_gnc(unit, params=params), scale)


def solve_pruned(
    problem: WeightedTLSProblem,
    *,
    params: GNCParams | None = None,
    pruning: PruningParams | None = None,
) -> RegistrationResult:
    """Max-clique pruning, GNC on the survivors and exact per-axis translation voting.

    The consistency graph ignores weights; correspondences of zero weight are left out of it.
    The problem is scaled to unit size first.

    Raises
    ------
    MemoryError
        When the dense consistency graph (N^2 bytes) does not fit in the available memory;
        raised before anything is allocated.
    """
    check_problem(problem)
    unit, scale = to_unit_scale(problem)
    return from_unit_scale(_solve_pruned(unit, params=params, pruning=pruning), scale)


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
    and the pose of lower TLS cost is returned; ``solve_time`` covers both. The problem is
    scaled to unit size first (exactly, by a power of two), so points at any finite scale
    (1e-200 .. 1e200) and tiny noise bounds are solved alike.

    Raises
    ------
    MemoryError
        ``method="pruned"`` with more correspondences than the memory's consistency graph holds.
    """
    check_problem(problem)
    if method not in ("auto", "gnc", "pruned"):
        raise ValueError(f"`method` must be 'auto', 'gnc' or 'pruned', got {method!r}.")
    unit, scale = to_unit_scale(problem)
    return from_unit_scale(_solve_registration(unit, method=method, gnc=gnc, pruning=pruning), scale)
