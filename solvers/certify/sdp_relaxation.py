"""SDP relaxations of a :class:`~solvers.certify.relaxation.Lifting`, solved with cvxpy + Clarabel.

Two relaxations of the arrowhead lifting:

* ``"dense"``: one PSD matrix ``Z`` of size ``d (K + 1)`` with ``Z_kk = Z_00`` and the redundant
  constraints "every off-diagonal block is symmetric" (QUASAR). Tightest, but an interior-point
  solve grows like ``K^6``.
* ``"chordal"``: the cost and constraints touch only the blocks ``(0, 0)``, ``(0, k)``, ``(k, k)``,
  an arrowhead (chordal) pattern whose cliques are ``{0, k}``. Keeping the redundant constraints
  inside the cliques only, the relaxation is ``K`` small PSD cones
  ``[[Z_00, Y_k], [Y_k, Z_00]] >= 0`` with symmetric ``Y_k``, sharing ``Z_00``.

The lower bound never trusts the solver's objective. From the PSD dual(s) returned by the
backend, the dual point is *repaired* so that every dual equality holds exactly (off-diagonal
blocks get their symmetric part from ``C``; the residual of the ``Z_00`` stationarity equation
is fitted by the pose-constraint multipliers and the rest moved into the diagonal blocks), and

    ``f_lb = b^T y - nu^T c + sum_i M_i min(lambda_min(S_i), 0)``

with ``M_i`` a bound on the trace of PSD block ``i`` over the feasible set. This is a valid
bound for *any* dual point, so an early-stopped or inexact solve still gives a valid (if weak)
bound.
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from solvers.certify.relaxation import Lifting

__all__ = ["RelaxationSolution", "solve_relaxation", "BACKEND_STATUS"]

log = logging.getLogger(__name__)

Kind = Literal["dense", "chordal"]

# cvxpy status -> (accepted for a certificate, closed certificate status).
BACKEND_STATUS: dict[str, tuple[bool, str]] = {
    "optimal": (True, "solved"),
    "optimal_inaccurate": (False, "inaccurate"),
    "user_limit": (False, "iteration_limit"),
    "infeasible": (False, "infeasible"),
    "infeasible_inaccurate": (False, "infeasible"),
    "unbounded": (False, "unbounded"),
    "unbounded_inaccurate": (False, "unbounded"),
    "solver_error": (False, "solver_error"),
}


@dataclass(frozen=True)
class RelaxationSolution:
    """What one relaxation solve gives.

    Attributes
    ----------
    lower_bound : float
        Recomputed sound lower bound (``-inf`` when no dual point was available).
    accepted : bool
        The backend reached its tolerances (a certificate may be issued).
    status : str
        Closed status: ``"solved"``, ``"inaccurate"``, ``"iteration_limit"``, ``"infeasible"``,
        ``"unbounded"``, ``"solver_error"``.
    backend_status : str
        The raw backend status.
    Z00 : (d, d) ndarray or None
        The primal moment block of the pose vector.
    eigenvalue_ratio : float
        ``lambda_1 / lambda_2`` of ``Z_00`` (large means rank one).
    sdp_objective : float
        The backend's own objective (diagnostic only).
    min_eig : float
        Smallest eigenvalue of the repaired dual matrix (diagnostic).
    solve_time : float
        Seconds, model building included.
    iterations : int
    message : str
    """

    lower_bound: float
    accepted: bool
    status: str
    backend_status: str
    Z00: NDArray[np.float64] | None
    eigenvalue_ratio: float
    sdp_objective: float
    min_eig: float
    solve_time: float
    iterations: int
    message: str


def _skew(M: NDArray[np.float64]) -> NDArray[np.float64]:
    return (M - np.swapaxes(M, -1, -2)) / 2


def _fit_multipliers(
    lift: Lifting, R: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Pose-constraint multipliers ``(y, nu >= 0)`` fitting ``R ~ sum y_l A_l - sum nu_j G_j``.

    Returns ``y``, ``nu`` and the residual (which the caller moves into a diagonal block).
    """
    L, J = lift.eq_mats.shape[0], lift.ineq_mats.shape[0]
    basis = np.concatenate([lift.eq_mats, -lift.ineq_mats]).reshape(L + J, -1).T
    coef = np.linalg.lstsq(basis, R.ravel(), rcond=None)[0]
    if J and np.any(coef[L:] < 0):
        # nu must be non-negative: drop the offending inequalities and refit.
        keep = np.concatenate([np.ones(L, bool), coef[L:] >= 0])
        coef = np.zeros(L + J)
        coef[keep] = np.linalg.lstsq(basis[:, keep], R.ravel(), rcond=None)[0]
        coef[L:] = np.maximum(coef[L:], 0.0)
    y, nu = coef[:L], coef[L:]
    resid = R - (np.tensordot(y, lift.eq_mats, 1) - np.tensordot(nu, lift.ineq_mats, 1))
    return y, nu, (resid + resid.T) / 2


def _offdiag_sym(lift: Lifting, Sym: NDArray[np.float64], C: NDArray[np.float64]) -> NDArray[np.float64]:
    """Symmetric part of off-diagonal dual blocks: ``C + sum_l y_l A_l`` over homogeneous ``A_l``.

    ``Sym`` (..., d, d) is the solver's symmetric part; the fitted multipliers of the product
    constraints ``<A_l, Z_ij> = 0`` (``b_l = 0``) are kept, the rest of the part is reset to ``C``.
    """
    hom = lift.eq_mats[lift.eq_rhs == 0]
    if hom.shape[0] == 0:
        return C
    basis = hom.reshape(hom.shape[0], -1).T
    D = (Sym - C).reshape(-1, basis.shape[0]).T
    coef = np.linalg.lstsq(basis, D, rcond=None)[0]
    return C + (basis @ coef).T.reshape(C.shape)


def bound_from_dense_dual(lift: Lifting, S: NDArray[np.float64], *, redundant: bool = True) -> tuple[float, float]:
    """Repair a dense dual matrix ``S`` (n, n) and return ``(lower_bound, min_eig)``."""
    K, d = lift.K, lift.d
    S = np.array(S, dtype=np.float64)
    S = (S + S.T) / 2
    blocks = S.reshape(K + 1, d, K + 1, d).transpose(0, 2, 1, 3).copy()  # [i, j] -> d x d
    C = np.zeros_like(blocks)
    C[0, 0] = lift.C00
    C[0, 1:] = lift.B
    C[1:, 0] = lift.B
    off = ~np.eye(K + 1, dtype=bool)
    if redundant:
        sym = (blocks[off] + np.swapaxes(blocks[off], 1, 2)) / 2
        blocks[off] = _offdiag_sym(lift, sym, C[off]) + _skew(blocks[off])
    else:
        blocks[off] = C[off]
    diag_sum = np.einsum("kkab->ab", blocks)
    y, nu, resid = _fit_multipliers(lift, lift.C00 - diag_sum)
    for k in range(K + 1):
        blocks[k, k] += resid / (K + 1)
    S = blocks.transpose(0, 2, 1, 3).reshape(d * (K + 1), d * (K + 1))
    ev = np.linalg.eigvalsh((S + S.T) / 2)
    lam = float(ev[0])
    lb = float(y @ lift.eq_rhs - nu @ lift.ineq_rhs + lift.trace_bound * (K + 1) * min(lam, 0.0))
    return lb - _rounding_allowance(lift, y, nu, ev, K + 1), lam


def _rounding_allowance(
    lift: Lifting, y: NDArray[np.float64], nu: NDArray[np.float64], ev: NDArray[np.float64],
    blocks: int,
) -> float:
    """A bound on the floating-point error of ``f_lb`` (subtracted from it).

    A computed eigenvalue is within ``n eps ||S||_2`` of the exact one (symmetric eigensolvers
    are backward stable; ``n`` is generous), scaled by the trace bound it is multiplied with;
    the dual objective's dot products add ``m eps sum |y_l b_l|``. Measured without it: with
    ``|a| / beta`` about 2.5e4 a bound exceeded the exact minimum by 3e-8.
    """
    eps = np.finfo(np.float64).eps
    n = lift.d * blocks
    norm = float(np.max(np.abs(ev))) if ev.size else 0.0
    dots = float(np.abs(y) @ np.abs(lift.eq_rhs) + np.abs(nu) @ np.abs(lift.ineq_rhs))
    return 4.0 * eps * (n * lift.trace_bound * blocks * norm + (y.size + nu.size + 1) * dots)


def bound_from_clique_duals(lift: Lifting, S: NDArray[np.float64]) -> tuple[float, float]:
    """Repair clique duals ``S`` (K, 2d, 2d) and return ``(lower_bound, min_eig)``."""
    K, d = lift.K, lift.d
    S = np.array(S, dtype=np.float64)
    S = (S + np.swapaxes(S, 1, 2)) / 2
    sym = (S[:, :d, d:] + np.swapaxes(S[:, :d, d:], 1, 2)) / 2
    off = _offdiag_sym(lift, sym, lift.B) + _skew(S[:, :d, d:])
    S[:, :d, d:] = off
    S[:, d:, :d] = np.swapaxes(off, 1, 2)
    diag_sum = S[:, :d, :d].sum(0) + S[:, d:, d:].sum(0)
    y, nu, resid = _fit_multipliers(lift, lift.C00 - diag_sum)
    S[:, :d, :d] += resid / (2 * K)
    S[:, d:, d:] += resid / (2 * K)
    ev = np.linalg.eigvalsh(S)
    lam = ev[:, 0]
    lb = float(y @ lift.eq_rhs - nu @ lift.ineq_rhs
               + 2 * lift.trace_bound * np.minimum(lam, 0.0).sum())
    return lb - _rounding_allowance(lift, y, nu, ev.ravel(), 2 * K), float(lam.min())


def _pose_constraints(cp, lift: Lifting, Z00):  # type: ignore[no-untyped-def]
    cons = [cp.trace(lift.eq_mats[i] @ Z00) == lift.eq_rhs[i] for i in range(len(lift.eq_rhs))]
    cons += [cp.trace(lift.ineq_mats[j] @ Z00) <= lift.ineq_rhs[j] for j in range(len(lift.ineq_rhs))]
    return cons


def solve_relaxation(
    lift: Lifting,
    *,
    kind: Kind = "chordal",
    max_iter: int = 200,
    eps: float = 1e-7,
    product_constraints: bool = True,
    time_limit: float | None = None,
    verbose: bool = False,
) -> RelaxationSolution:
    """Solve a relaxation of ``lift`` with Clarabel through cvxpy and bound it soundly.

    Never raises on a backend failure: the outcome is in ``status`` / ``message``.

    Parameters
    ----------
    lift : Lifting
    kind : {"chordal", "dense"}
    max_iter : int
        Clarabel's iteration limit.
    eps : float
        Clarabel's gap and feasibility tolerances.
    product_constraints : bool
        Add ``<A_l, Z_ij> = 0`` on off-diagonal blocks for the homogeneous pose constraints
        (``theta_k`` times a pose constraint); they make the joint lifting tight.
    time_limit : float or None
        Clarabel's time limit in seconds.
    """
    import cvxpy as cp

    t0 = time.perf_counter()
    K, d = lift.K, lift.d
    Z00 = cp.Variable((d, d), symmetric=True)
    cons = _pose_constraints(cp, lift, Z00)
    # Products theta_k * (homogeneous pose constraint) hold on every off-diagonal block.
    hom = lift.eq_mats[lift.eq_rhs == 0] if product_constraints else lift.eq_mats[:0]
    if kind == "chordal":
        Y = cp.Variable((K * d, d))
        psd = []
        sym = []
        obj = cp.trace(lift.C00 @ Z00)
        Bs = np.concatenate(lift.B, axis=0)  # (K d, d)
        obj = obj + 2 * cp.sum(cp.multiply(Bs, Y))
        for k in range(K):
            Yk = Y[k * d:(k + 1) * d, :]
            sym.append(Yk == Yk.T)
            sym += [cp.trace(A @ Yk) == 0 for A in hom]
            psd.append(cp.bmat([[Z00, Yk], [Yk.T, Z00]]) >> 0)
        cons += sym + psd
    elif kind == "dense":
        n = d * (K + 1)
        Z = cp.Variable((n, n), symmetric=True)
        psd = [Z >> 0]
        cons += psd + [Z[:d, :d] == Z00]
        for k in range(1, K + 1):
            cons.append(Z[k * d:(k + 1) * d, k * d:(k + 1) * d] == Z00)
        for i in range(K + 1):
            for j in range(i + 1, K + 1):
                blk = Z[i * d:(i + 1) * d, j * d:(j + 1) * d]
                cons.append(blk == blk.T)
                cons += [cp.trace(A @ blk) == 0 for A in hom]
        obj = cp.trace(lift.dense_cost() @ Z)
    else:
        raise ValueError(f"`kind` must be 'chordal' or 'dense', got {kind!r}.")
    prob = cp.Problem(cp.Minimize(obj), cons)
    status, message, it = "solver_error", "", 0
    raw = "not_run"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            opts = {} if time_limit is None else {"time_limit": float(time_limit)}
            prob.solve(solver=cp.CLARABEL, verbose=verbose, max_iter=int(max_iter),
                       tol_gap_abs=eps, tol_gap_rel=eps, tol_feas=eps, **opts)
        raw = str(prob.status)
    except cp.error.SolverError as exc:  # backend failed: report, never raise
        raw, message = "solver_error", f"SDP backend failed: {exc}"
    except (ValueError, ArithmeticError) as exc:
        raw, message = "solver_error", f"SDP model could not be solved: {exc}"
    accepted, status = BACKEND_STATUS.get(raw, (False, "solver_error"))
    try:
        it = int(prob.solver_stats.num_iters or 0)
    except Exception:  # noqa: BLE001 - stats are absent after a failure
        it = 0
    lb, lam = -np.inf, np.nan
    duals = [c.dual_value for c in psd]
    if all(v is not None for v in duals):
        if kind == "chordal":
            lb, lam = bound_from_clique_duals(lift, np.asarray(duals))
        else:
            lb, lam = bound_from_dense_dual(lift, duals[0])
        if not np.isfinite(lb):
            lb = -np.inf
    elif not message:
        message = f"the backend returned no dual point (status {raw})"
    Zv = Z00.value
    ratio = np.nan
    if Zv is not None and np.all(np.isfinite(Zv)):
        ev = np.linalg.eigvalsh((Zv + Zv.T) / 2)
        ratio = float(ev[-1] / max(ev[-2], 1e-300)) if ev[-1] > 0 else np.nan
    else:
        Zv = None
    if not message:
        message = f"Clarabel status {raw}"
    val = prob.value
    return RelaxationSolution(
        lower_bound=float(lb),
        accepted=bool(accepted and np.isfinite(lb)),
        status=status,
        backend_status=raw,
        Z00=None if Zv is None else np.asarray(Zv),
        eigenvalue_ratio=ratio,
        sdp_objective=float(val) if val is not None and np.isfinite(val) else np.nan,
        min_eig=lam,
        solve_time=time.perf_counter() - t0,
        iterations=it,
        message=message,
    )
