"""Certifiable registration: SDP relaxations of weighted TLS with sound duality-gap certificates.

Public entry points
-------------------
* :func:`solve_sdp` -- the relaxation's own rounded and locally refined pose, with its certificate.
* :func:`certify_result` -- attach a certificate to a solver's result (or return a better pose).
* :func:`certify_pose` -- certify any candidate pose.

Which problem is bounded (``scope``)
------------------------------------
* ``"full"`` (the default, ``"auto"``): the weighted TLS problem as given, bounded by
  **clique decomposition** (:mod:`solvers.certify.cliques`): every pose's inlier set is a
  clique of the pairwise-consistency graph (two inliers' translation-invariant measurements
  differ in length by at most ``cbar (beta_i + beta_j)``), hence lies in a maximal clique ``C``,
  and the pose's cost is exactly its cost on ``C`` plus ``cbar2`` times the weight outside
  ``C``. The least, over the maximal cliques that could beat the candidate, of (a certified
  bound on the subproblem restricted to ``C``) + (the outlier cost outside ``C``) is a lower
  bound on the full problem. A clique whose least-squares pose keeps every term inside the
  noise bound is bounded in closed form (:mod:`solvers.certify.all_inliers`: removing terms
  provably never pays, so the least-squares optimum is exact). Other clique subproblems (nearly
  all inliers) are solved exactly by
  branch and bound over its inlier sets (closed-form least squares per set); beyond the node
  budget (large cliques at low outlier rates) it is bounded by the joint relaxation's
  Douglas-Rachford dual search (:func:`solvers.certify.joint_dual.joint_dual_certificate`).
  When the maximal cliques are too many to list (real-feature scans) and the caller asks for
  it (``pose_search``), a branch and bound over poses bounds the problem instead
  (:mod:`solvers.certify.pose_bnb`), proving gaps from loose to ``tol`` while time remains.
  Correspondences that share a source point also bound it, each source point's image placed
  freely and pairs of them at their distance (:mod:`solvers.certify.groups`); the larger of the
  two bounds is kept.
  ``method="dense"``/``"chordal"``/``"dual"`` bound the whole problem with the joint
  relaxation (lifting ``y = [1; vec(R); t]``) instead.
* ``"pruned"``: the joint relaxation of the problem restricted to the max-clique survivors.
* ``"rotation"``: the rotation subproblem over translation-invariant measurements (a chain of
  TIMs through the max-clique survivors), QUASAR's quaternion relaxation: what TEASER++'s
  certifier bounds. A dual certificate of the candidate is searched by Douglas-Rachford
  splitting from a closed-form dual point in the candidate's frame
  (:func:`solvers.certify.sdp_dual.rotation_dual_certificate`), with the dense interior-point
  solve as the fallback for ``K <= dense_max``.

What a certificate vouches for
------------------------------
A certificate is attached to exactly one pose: its ``upper_bound`` is that pose's cost on the
bounded problem (in the user's units). Every relaxation bound is recomputed in numpy from a
dual point with the eigenvalue correction and a rounding allowance (the backend's objective is
never used); a branch-and-bound value is an exact minimum less a rounding allowance. ``certified`` needs a backend that reached its tolerances (or a dual iteration that
reached its target) *and* a small gap on the normalised problem, not diluted by the outliers'
constant cost (:func:`solvers.certificate.undiluted_gap`; the literature's gap is reported
beside it). When certifying finds a better optimum of the bounded problem, the certificate
says so (``better_upper_bound``); :func:`certify_result` returns that pose only if its cost on
the user's problem is not higher, and then certifies *it*.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.certificate import (
    BoundedProblem,
    Certificate,
    CertificateStatus,
    relative_gap,
    undiluted_gap,
)
from solvers.certify._threads import single_thread_blas
from solvers.certify.relaxation import (
    Lifting,
    RotationTLSProblem,
    joint_lifting,
    refine_rotation,
    rotation_lifting,
    tim_problem,
)
from solvers.problem import WeightedTLSProblem
from solvers.procrustes import weighted_procrustes
from solvers.result import RegistrationResult, SolverStatus

__all__ = [
    "certify_pose",
    "certify_result",
    "solve_sdp",
    "certify_rotation",
    "rotation_gnc",
    "refine_pose",
    "refine_rotation",
    "refine_translation",
    "rebuild_bounded_problem",
    "ROTATION_ATOL",
]

log = logging.getLogger(__name__)

DEFAULT_DUAL_TIME_LIMIT = 120.0
"""Seconds the dual certificate search may take when no ``time_limit`` is given."""

ROTATION_ATOL = 1e-9
"""Absolute tolerance on ``|R^T R - I|`` (max entry) and ``|det R - 1|`` for a candidate.

A matrix off by more bounds another problem's cost: a rotation scaled by ``1 + 5e-6`` (accepted
by ``np.allclose``'s default relative tolerance) was once "certified" with ``upper < lower``."""

MAX_CLIQUES = 5000
"""Most maximal cliques the clique decomposition bounds before giving up (uncertified)."""
LISTING_SHARE = 0.25
"""Share of the time limit the listing of maximal cliques may take (as a node budget)."""
LISTING_NODES_PER_SECOND = 400_000
"""Branches per second of the maximal-clique listing (measured 340,000 on the 3DMatch pair's
927-vertex core, load average 10 on 2 cores), for its time limit."""
POSE_SHARE = 0.6
"""Share of the time limit the branch and bound over poses may take when a subproblem's
certificate follows (``rotation_fallback``)."""
POSE_DEFAULT_TIME = 10.0
"""Seconds the branch and bound over poses may take when no ``time_limit`` is given."""
CLIQUE_WORK_PER_SECOND = 100_000_000
"""Adjacency look-ups per second of the maximum-clique search (for its time limit)."""

MIN_NODES_FOR_RATE = 20_000
"""Exact searches of fewer nodes (well under 10 ms) are not used to measure the machine's
speed: their fixed costs would look like a slowdown."""

BNB_MAX_TERMS = 200
"""Largest clique the exact search tries (N = 100 at 0% outliers: 4-12 M nodes, seconds; a
clique of 500 did not finish in 18 M nodes)."""

JOINT_DUAL_MAX = 60
"""Largest clique handed to the joint dual search when the exact search runs out of budget: its
dual matrix has ``13 (K + 1)`` rows, and past about 60 terms an iteration takes seconds."""

BNB_MAX_NODES = 50_000_000
"""Node budget of the exact branch and bound on one clique (about 25 s); beyond it the clique
subproblem goes to the joint dual search."""

Scope = Literal["auto", "full", "pruned", "rotation"]
Method = Literal["auto", "dense", "chordal", "dual"]

# Relaxation status (solvers.certify.sdp_relaxation) -> certificate status.
_STATUS_TABLE: dict[str, CertificateStatus] = {
    "solved": CertificateStatus.GAP_TOO_LARGE,  # refined to CERTIFIED when the gap is small
    "inaccurate": CertificateStatus.INACCURATE,
    "iteration_limit": CertificateStatus.ITERATION_LIMIT,
    "infeasible": CertificateStatus.INFEASIBLE,
    "unbounded": CertificateStatus.UNBOUNDED,
    "solver_error": CertificateStatus.SOLVER_ERROR,
}


@dataclass(frozen=True)
class _Bound:
    lower: float
    accepted: bool
    status: CertificateStatus
    backend_status: str
    eigenvalue_ratio: float
    method: str
    message: str
    Z00: NDArray[np.float64] | None = None
    rotation: NDArray[np.float64] | None = None  # a better candidate found by the search
    translation: NDArray[np.float64] | None = None
    cliques: tuple[tuple[int, ...], ...] | None = None


# ----------------------------------------------------------------------------- helpers
def _check_tol(tol: float) -> float:
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"`tol` must be a positive finite scalar, got {tol!r}.")
    return float(tol)


def _candidate_error(R: Any, t: Any) -> tuple[NDArray[np.float64], NDArray[np.float64], str]:
    """Shape-check the candidate (raising ``ValueError``); report non-finite / non-rotation."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"Expected `R` to have shape (3, 3), got {R.shape}.")
    if t.size != 3:
        raise ValueError(f"Expected `t` to have shape (3,), got {t.shape}.")
    t = t.reshape(3)
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return R, t, "the candidate pose contains NaN or inf"
    orth = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if orth > ROTATION_ATOL or abs(det - 1.0) > ROTATION_ATOL:
        return R, t, (f"the candidate `R` is not a rotation matrix (max |R^T R - I| = {orth:.2e}, "
                      f"det = {det:.12g}; tolerance {ROTATION_ATOL:g}); project it onto SO(3) "
                      f"first, e.g. with scipy.spatial.transform.Rotation.from_matrix")
    return R, t, ""


def _survivors(problem: WeightedTLSProblem) -> NDArray[np.int64]:
    from solvers.registration.pruning import prune_max_clique

    active = np.flatnonzero(problem.weights > 0)
    if active.size < 3:
        return np.arange(problem.n)
    clique, _, _ = prune_max_clique(
        problem.source[active], problem.target[active], problem.noise_bound[active], problem.cbar2
    )
    return active[clique] if clique.size >= 2 else np.arange(problem.n)


# ----------------------------------------------------------------------------- local solvers
def rotation_gnc(
    problem: RotationTLSProblem, *, max_iterations: int = 100, mu_factor: float = 1.4
) -> NDArray[np.float64]:
    """GNC-TLS for a rotation-only TLS problem, by the registration's GNC kernel.

    The terms are mirrored (``a, b`` and ``-a, -b``, interleaved): mirrored terms have equal
    residuals for every rotation, hence equal GNC weights, so every weighted centroid is exactly
    zero and the pose GNC's translation stays 0 -- it solves the rotation problem (each cost
    counted twice). The rotation is then refined locally.
    """
    from solvers.registration import GNCParams, solve_registration

    n = problem.n
    a = np.empty((2 * n, 3))
    b = np.empty((2 * n, 3))
    a[0::2], a[1::2] = problem.source, -problem.source
    b[0::2], b[1::2] = problem.target, -problem.target
    mirrored = WeightedTLSProblem(a, b, noise_bound=np.repeat(problem.noise_bound, 2),
                                  weights=np.repeat(problem.weights, 2), cbar2=problem.cbar2)
    res = solve_registration(mirrored, method="gnc",
                             gnc=GNCParams(max_iterations=max_iterations, mu_factor=mu_factor))
    return refine_rotation(problem, res.rotation)


def _dual_candidate(problem: RotationTLSProblem, R: NDArray[np.float64]) -> NDArray[np.float64]:
    """The best of: ``R`` refined, GNC, and GNC on the norm-consistent terms (all refined).

    A dual certificate exists only at the optimum, so the dual search starts from the best
    rotation found. Every inlier of every rotation has ``| |b| - |a| | <= beta cbar``, so GNC
    on those terms alone survives more outliers (measured: K = 20 at 80% outliers, GNC on all
    terms missed the optimum in 8 of 40 instances).
    """
    cands = [refine_rotation(problem, R), rotation_gnc(problem)]
    gap = np.abs(np.linalg.norm(problem.target, axis=1) - np.linalg.norm(problem.source, axis=1))
    keep = (gap <= problem.noise_bound * np.sqrt(problem.cbar2)) & (problem.weights > 0)
    if 2 <= keep.sum() < problem.n:
        sub = RotationTLSProblem(problem.source[keep], problem.target[keep],
                                 noise_bound=problem.noise_bound[keep],
                                 weights=problem.weights[keep], cbar2=problem.cbar2)
        cands.append(refine_rotation(problem, rotation_gnc(sub)))
    return min(cands, key=problem.cost)


def refine_pose(
    problem: WeightedTLSProblem, R: ArrayLike, t: ArrayLike, *, max_iterations: int = 50
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Local TLS refinement of a pose: inlier selection and weighted Procrustes, alternated."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    best = problem.cost(R, t)
    w0 = problem.weights / problem.noise_bound**2
    for _ in range(max_iterations):
        S = problem.inliers(R, t) & (w0 > 0)
        if S.sum() < 3:
            break
        R2, t2 = weighted_procrustes(problem.source[S], problem.target[S], w0[S])
        c = problem.cost(R2, t2)
        if not c < best - 1e-14 * max(1.0, best):
            break
        R, t, best = R2, t2, c
    return R, t


def refine_translation(
    problem: WeightedTLSProblem, R: ArrayLike, t: ArrayLike, *, max_iterations: int = 50
) -> NDArray[np.float64]:
    """Local TLS refinement of the translation with the rotation held: inlier selection and
    the inliers' weighted mean of ``b - R a``, alternated (a rotation certified on the rotation
    subproblem stays the certified one)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    best = problem.cost(R, t)
    v = problem.weights / problem.noise_bound**2
    d = problem.target - problem.source @ R.T
    for _ in range(max_iterations):
        S = problem.inliers(R, t) & (v > 0)
        if not S.any():
            break
        t2 = (v[S] @ d[S]) / v[S].sum()
        c = problem.cost(R, t2)
        if not c < best - 1e-14 * max(1.0, best):
            break
        t, best = t2, c
    return t


# ----------------------------------------------------------------------------- bounds
def _ipm_bound(
    lift: Lifting, kind: str, max_iter: int, eps: float, time_limit: float | None = None
) -> _Bound:
    from solvers.certify.sdp_relaxation import solve_relaxation

    sol = solve_relaxation(lift, kind=kind, max_iter=max_iter, eps=eps,  # type: ignore[arg-type]
                           time_limit=time_limit)
    status = _STATUS_TABLE.get(sol.status, CertificateStatus.SOLVER_ERROR)
    if sol.status == "solved" and not sol.accepted:
        status = CertificateStatus.SOLVER_ERROR
    return _Bound(
        lower=sol.lower_bound,
        accepted=sol.accepted,
        status=status,
        backend_status=f"clarabel:{sol.backend_status}",
        eigenvalue_ratio=sol.eigenvalue_ratio,
        method=kind,
        message=sol.message,
        Z00=sol.Z00,
    )


def _rotation_bound(
    rp: RotationTLSProblem,
    R: NDArray[np.float64],
    *,
    method: Method,
    tol: float,
    max_iter: int | None,
    time_limit: float | None,
    dense_max: int,
    eps: float,
    outlier_cost: float = 0.0,
) -> _Bound:
    """``outlier_cost``: the candidate's (normalised), the constant of the verdict's gap, which
    the dual search then reaches rather than the looser literature gap.

    Terms that no rotation makes inliers (``| ||b|| - ||a|| | > cbar beta``: ``||R a - b||`` is
    at least that) cost ``cbar2 w`` everywhere: they are bounded by that constant exactly and
    left out of the relaxation, which is not tight on them (measured: 99 such terms of 99, a
    relaxation bound 0.1 below the exact 99)."""
    norm_gap = np.abs(np.linalg.norm(rp.target, axis=1) - np.linalg.norm(rp.source, axis=1))
    slack = 8 * np.finfo(np.float64).eps * (np.linalg.norm(rp.target, axis=1)
                                             + np.linalg.norm(rp.source, axis=1))
    never = norm_gap > rp.noise_bound * np.sqrt(rp.cbar2) * (1 + 1e-9) + slack
    if never.any():
        const = rp.cbar2 * float(rp.weights[never].sum())
        const -= 8 * np.finfo(np.float64).eps * const  # rounding of the sum
        if never.all():
            return _Bound(lower=const, accepted=True, status=CertificateStatus.GAP_TOO_LARGE,
                          backend_status="closed_form", eigenvalue_ratio=np.nan,
                          method="closed_form",
                          message="no rotation makes any term an inlier (norms differ by more "
                                  "than the noise bound)")
        keep = ~never
        sub = RotationTLSProblem(rp.source[keep], rp.target[keep],
                                 noise_bound=rp.noise_bound[keep], weights=rp.weights[keep],
                                 cbar2=rp.cbar2)
        b = _rotation_bound(sub, R, method=method, tol=tol, max_iter=max_iter,
                            time_limit=time_limit, dense_max=dense_max, eps=eps,
                            outlier_cost=max(outlier_cost - const, 0.0))
        return dataclasses.replace(
            b, lower=b.lower + const,
            message=f"{b.message}; {int(never.sum())} terms that no rotation makes inliers "
                    f"bounded by their outlier cost")
    lift = rotation_lifting(rp)
    if method in ("auto", "dual"):
        # Measured: the identity-frame dual search certifies K = 100 in 2-7 iterations
        # (0.1-0.3 s); the interior point remains the fallback for small K.
        start = time.perf_counter()
        drs = _quaternion_drs_bound(rp, R, tol, max_iter or 500, time_limit, outlier_cost)
        if method == "dual" or drs.status is CertificateStatus.GAP_TOO_LARGE or rp.n > dense_max:
            return drs
        # The fallback shares the caller's time budget rather than getting a fresh one.
        remaining = None if time_limit is None else time_limit - (time.perf_counter() - start)
        if remaining is not None and remaining <= 0.0:
            return drs
        ipm = _ipm_bound(lift, "dense", 200, eps, remaining)
        return ipm if ipm.accepted and ipm.lower >= drs.lower else drs
    return _ipm_bound(lift, method, max_iter or 200, eps, time_limit)


def _quaternion_drs_bound(
    rp: RotationTLSProblem, R: NDArray[np.float64], tol: float, max_iter: int,
    time_limit: float | None, outlier_cost: float = 0.0,
) -> _Bound:
    from solvers.certify.sdp_dual import rotation_dual_certificate

    if time_limit is None:
        time_limit = DEFAULT_DUAL_TIME_LIMIT
    with single_thread_blas():
        res = rotation_dual_certificate(rp, R, tol=tol, max_iterations=max_iter,
                                        time_limit=time_limit, outlier_cost=outlier_cost)
    return _dual_search_bound(res, "dual certificate search (identity frame)")


def _dual_search_bound(res: Any, what: str) -> _Bound:
    """A :class:`_Bound` from a :class:`solvers.certify.sdp_dual.DualCertificateResult`."""
    status = CertificateStatus.GAP_TOO_LARGE if res.converged else CertificateStatus.ITERATION_LIMIT
    return _Bound(
        lower=res.lower_bound,
        accepted=True,  # the bound is recomputed from an exactly structured dual point
        status=status,
        backend_status=f"drs:{'converged' if res.converged else 'stopped'} after "
        f"{res.iterations} iterations",
        eigenvalue_ratio=float("nan"),
        method="dual_drs",
        message=f"{what}, min eigenvalue {res.min_eig:.3g}",
        rotation=res.rotation,
    )


def _joint_bound(
    problem: WeightedTLSProblem,
    R: NDArray[np.float64],
    t: NDArray[np.float64],
    *,
    method: Method,
    tol: float,
    max_iter: int | None,
    time_limit: float | None,
    dense_max: int,
    eps: float,
    outlier_cost: float = 0.0,
) -> _Bound:
    lift = joint_lifting(problem)
    if method == "auto":
        # The chordal relaxation is loose on the full problem (measured gap 0.35-0.46 at
        # K = 10-20); the dual search reaches the tight dense relaxation's bound.
        method = "dense" if problem.n <= dense_max else "dual"
    if method == "dual":
        return _joint_drs_bound(problem, R, t, tol, max_iter or 3000, time_limit, outlier_cost)
    return _ipm_bound(lift, method, max_iter or 200, eps, time_limit)


def _joint_drs_bound(
    problem: WeightedTLSProblem, R: NDArray[np.float64], t: NDArray[np.float64], tol: float,
    max_iter: int, time_limit: float | None, outlier_cost: float = 0.0,
) -> _Bound:
    from solvers.certify.joint_dual import joint_dual_certificate

    # A dual certificate exists only at a stationary point: refine the candidate first.
    Rr, tr = refine_pose(problem, R, t)
    if problem.cost(Rr, tr) > problem.cost(R, t):
        Rr, tr = R, t
    with single_thread_blas():
        res = joint_dual_certificate(problem, Rr, tr, tol=tol, max_iterations=max_iter,
                                     time_limit=DEFAULT_DUAL_TIME_LIMIT if time_limit is None
                                     else time_limit, outlier_cost=outlier_cost)
    bound = _dual_search_bound(res, "joint dual certificate search")
    return dataclasses.replace(bound, rotation=Rr, translation=tr)


# ----------------------------------------------------------------------------- scoping
@dataclass(frozen=True, eq=False)
class _Scoped:
    """The bounded problem (user units) and how it was built from the user's problem."""

    label: BoundedProblem
    problem: WeightedTLSProblem | RotationTLSProblem
    indices: NDArray[np.int64] | None  # terms of the user's problem; None = all
    pairs: NDArray[np.int64] | None  # TIM pairs (user indices)


def _scope_problem(problem: WeightedTLSProblem, scope: Scope, survivors: ArrayLike | None) -> _Scoped:
    """The bounded problem for ``scope`` (``"auto"`` is ``"full"``)."""
    if scope not in ("auto", "full", "pruned", "rotation"):
        raise ValueError(f"`scope` must be 'auto', 'full', 'pruned' or 'rotation', got {scope!r}.")
    if scope in ("auto", "full"):
        return _Scoped(BoundedProblem.FULL, problem, None, None)
    idx = _survivors(problem) if survivors is None else np.asarray(survivors, dtype=np.int64)
    if idx.ndim != 1 or (idx.size and (idx.min() < 0 or idx.max() >= problem.n)):
        raise ValueError(f"`survivors` must be indices in [0, {problem.n}), got shape {idx.shape}.")
    if idx.size < 3:
        idx = np.arange(problem.n)
    if scope == "pruned":
        return _Scoped(BoundedProblem.PRUNED, problem.subset(idx), idx, None)
    chain = np.stack([idx[:-1], idx[1:]], axis=1)
    return _Scoped(BoundedProblem.ROTATION_TIM, tim_problem(problem, chain), idx, chain)


def rebuild_bounded_problem(
    problem: WeightedTLSProblem, certificate: Certificate
) -> WeightedTLSProblem | RotationTLSProblem:
    """The problem a certificate of a pose for ``problem`` bounds, rebuilt from its record.

    Its ``upper_bound`` is the certified pose's cost on the returned problem and its
    ``lower_bound`` a bound on that problem's optimum (user units).
    """
    if certificate.problem == BoundedProblem.FULL.value:
        return problem
    if certificate.problem == BoundedProblem.PRUNED.value and certificate.indices is not None:
        return problem.subset(np.asarray(certificate.indices, dtype=np.int64))
    if certificate.problem == BoundedProblem.ROTATION_TIM.value and certificate.pairs is not None:
        return tim_problem(problem, np.asarray(certificate.pairs, dtype=np.int64).reshape(-1, 2))
    raise ValueError(f"The certificate ({certificate.problem}) does not record its bounded "
                     f"problem's terms.")


def _normalised(p: WeightedTLSProblem | RotationTLSProblem) -> tuple[Any, float]:
    """The problem with weights divided by their positive mean, and that scale.

    The cost then counts one average correspondence's outlier cost as ``cbar2``: gaps do not
    depend on the weights' units (the liftings centre and scale the points themselves).
    """
    pos = p.weights[p.weights > 0]
    ws = float(pos.mean()) if pos.size else 1.0
    if not (np.isfinite(ws) and ws > 0):
        ws = 1.0
    cls = type(p)
    return cls(p.source, p.target, noise_bound=p.noise_bound, weights=p.weights / ws,
               cbar2=p.cbar2), ws


def _cost(p: WeightedTLSProblem | RotationTLSProblem, R: NDArray[np.float64],
          t: NDArray[np.float64] | None) -> float:
    return p.cost(R) if isinstance(p, RotationTLSProblem) else p.cost(R, t)


def _outlier_cost(p: WeightedTLSProblem | RotationTLSProblem, R: NDArray[np.float64],
                  t: NDArray[np.float64] | None) -> float:
    r2 = p.residuals_sq(R) if isinstance(p, RotationTLSProblem) else p.residuals_sq(R, t)
    return float(p.cbar2 * p.weights[r2 > p.cbar2].sum())


# ----------------------------------------------------------------------------- clique route
def _clique_number_best_gap(pn: WeightedTLSProblem, R: NDArray[np.float64],
                            t: NDArray[np.float64]) -> tuple[float, int]:
    """The smallest gap the clique-number bound could give ``(R, t)`` on ``pn``, and the
    candidate's strict inlier count ``k``.

    The candidate's strict inliers form a clique of at least ``s_min`` terms (they weigh more
    than the threshold of :func:`solvers.certify.cliques.candidate_cliques`), so the clique
    number of the core is ``omega >= k`` and the bound is at most ``cbar2 (W - the k largest
    weights)``; the gap (:func:`solvers.certificate.undiluted_gap`) only grows as the bound
    falls.
    """
    r2 = pn.residuals_sq(R, t)
    k = int(np.count_nonzero((r2 < pn.cbar2) & (pn.weights > 0)))
    ws = np.sort(pn.weights[pn.weights > 0])[::-1]
    best = pn.cbar2 * (float(pn.weights.sum()) - float(ws[:k].sum()))
    return undiluted_gap(pn.cost(R, t), best, _outlier_cost(pn, R, t)), k


def _shared_source(pn: WeightedTLSProblem) -> tuple[Any, str]:
    """The bound of correspondences sharing a source point (eq. (2)'s candidates per model
    point; :mod:`solvers.certify.groups`), sound whatever the cliques give, and the message's
    clause naming it ("" when it is 0, as for one-to-one correspondences)."""
    from solvers.certify.groups import shared_source_bound

    shared = shared_source_bound(pn)
    note = (f"; bounded by the correspondences of each source point placed independently "
            f"({shared.groups} source points with several"
            + (f", {shared.pairs} pairs of them kept at their distance" if shared.pairs else "")
            + "; the rest of the rigid motion left out)" if shared.lower > 0 else "")
    return shared, note


def _clique_bound(
    pn: WeightedTLSProblem, R: NDArray[np.float64], t: NDArray[np.float64], *, tol: float,
    max_iter: int | None, time_limit: float | None, eps: float, skip_futile: bool = False,
    pose_search: bool = False,
) -> _Bound:
    """Lower bound on the (normalised) full problem by clique decomposition (module docstring).

    ``pose_search``: when the listing gives up, bound the problem by the branch and bound over
    poses (:mod:`solvers.certify.pose_bnb`) in ``POSE_SHARE`` of the time limit with
    ``skip_futile`` (its caller may certify a subproblem next), else all of it; the tighter of
    its bound and the others is kept.

    ``skip_futile``: when the listing gives up, the clique-number bound is not searched if it
    cannot certify whatever omega it finds (:func:`_clique_number_best_gap`); the bound is then
    the trivial ``0`` (TLS costs are non-negative).
    """
    from solvers.certify.all_inliers import all_inlier_bound
    from solvers.certify.cliques import (
        NODES_PER_SECOND,
        candidate_cliques,
        clique_number_bound,
        clique_optimum,
        small_clique_optimum,
    )

    t0 = time.perf_counter()
    budget = DEFAULT_DUAL_TIME_LIMIT if time_limit is None else time_limit
    u = pn.cost(R, t)
    # The listing's share of the time limit becomes a node budget (it cannot read the clock).
    cliques, complete = candidate_cliques(
        pn, u, limit=MAX_CLIQUES, max_nodes=int(budget * LISTING_SHARE * LISTING_NODES_PER_SECOND))
    if not complete:
        # Dense graphs (real features): too many maximal cliques to bound one by one. The
        # clique number still bounds every pose's inlier count: a weak but sound bound.
        shared, shared_note = _shared_source(pn)
        pose = None
        if pose_search:
            pose = _pose_search_bound(pn, R, t, tol=tol, time_limit=time_limit, t0=t0,
                                      share=POSE_SHARE if skip_futile else 1.0)
            if pose.status is CertificateStatus.GAP_TOO_LARGE or (
                    pose.lower >= shared.lower and skip_futile):
                return pose
        if skip_futile:
            best_gap, k = _clique_number_best_gap(pn, R, t)
            if best_gap > tol:
                return _Bound(
                    lower=min(shared.lower, u), accepted=True,
                    status=CertificateStatus.ITERATION_LIMIT,
                    backend_status="cliques:too_many; clique number not attempted",
                    eigenvalue_ratio=np.nan, method="shared_source" if shared.lower > 0 else "none",
                    message=(f"more than {MAX_CLIQUES} maximal cliques could beat the pose, or "
                             "too many to list within the time limit; the clique-number bound "
                             f"not attempted: even a clique number of {k} (the candidate's "
                             f"inliers) would leave a gap of {best_gap:.3g} > {tol:g}"
                             + (shared_note or "; bounded by 0 (TLS costs are non-negative)")))
        remaining = max(budget - (time.perf_counter() - t0), 0.0)
        lower = clique_number_bound(pn, u, max_work=int(remaining / 2 * CLIQUE_WORK_PER_SECOND))
        if pose is not None and pose.lower >= max(lower, shared.lower):
            return pose
        return _Bound(lower=min(max(lower, shared.lower), u), accepted=True,
                      status=CertificateStatus.ITERATION_LIMIT,
                      backend_status="cliques:too_many", eigenvalue_ratio=np.nan,
                      method="shared_source" if shared.lower > lower else "clique_number",
                      message=(f"more than {MAX_CLIQUES} maximal cliques could beat the pose, or "
                               "too many to list within the time limit; bounded by the clique "
                               "number (no pose keeps more inliers than the largest consistent "
                               "set)" + (shared_note.replace("; bounded", ", or, tighter here,")
                                         if shared.lower > lower else "")))
    total = float(pn.weights.sum())
    c2 = pn.cbar2
    r2 = pn.residuals_sq(R, t)
    # Cliques that could beat u: none left means u is optimal up to the skip threshold.
    lower = u * (1 + 1e-9) + 1e-12 * total
    best_R, best_t, best_u = None, None, u
    used: list[tuple[int, ...]] = []
    stopped, methods, iters = False, set(), []
    # The exact search's time limit is a node budget at a nominal rate; a loaded machine (or a
    # thread sharing the interpreter) runs slower, so budgets shrink by the slowdown measured
    # on the searches so far, and nothing is searched once the time is up.
    slowdown = 1.0
    for C in cliques:
        out_cost = c2 * (total - float(pn.weights[C].sum()))
        used.append(tuple(int(i) for i in C))
        remaining = budget - (time.perf_counter() - t0)
        if C.size < 3:  # closed form (a clique of one or two terms)
            methods.add("closed form")
            res = small_clique_optimum(pn, C, R)
            lower = min(lower, res.lower_bound + out_cost)
            if pn.cost(res.rotation, res.translation) < best_u:
                best_R, best_t = refine_pose(pn, res.rotation, res.translation)
                best_u = pn.cost(best_R, best_t)
            continue
        sub = pn.subset(C)
        u_sub = sub.cost(R, t)
        closed = all_inlier_bound(sub)  # closed form, O(K): before any budget check
        floor = 0.0 if closed is None else closed.lower  # f_C >= floor whatever else fails
        if closed is not None:
            if closed.cost < u_sub and pn.cost(closed.rotation, closed.translation) < best_u:
                Rc, tc = refine_pose(pn, closed.rotation, closed.translation)
                best_R, best_t, best_u = Rc, tc, pn.cost(Rc, tc)
            if closed.exact:  # removing terms never pays: the least-squares optimum is exact
                methods.add("all-inlier closed form")
                lower = min(lower, closed.lower + out_cost)
                continue
        if remaining <= 0:
            methods.add("time limit reached")
            stopped = True
            lower = min(lower, floor + out_cost)  # sound, if weak
            continue
        if C.size > BNB_MAX_TERMS:
            # Hopeless for the exact search (it grows exponentially with the clique's inlier
            # cost) and for the joint dual search: give up at once rather than at the deadline.
            methods.add(f"clique of {C.size} terms too large")
            stopped = True
            lower = min(lower, floor + out_cost)
            continue
        started = time.perf_counter()
        res = clique_optimum(sub, u_sub, np.argsort(-r2[C], kind="stable"),
                             max_nodes=BNB_MAX_NODES, time_limit=remaining / 2 / slowdown)
        if res.nodes >= MIN_NODES_FOR_RATE:
            rate = res.nodes / max(time.perf_counter() - started, 1e-9)
            slowdown = max(slowdown, NODES_PER_SECOND / rate)
        iters.append(res.nodes)
        if res.complete:
            methods.add("bnb")
            lb_sub = res.lower_bound
            if res.best_cost < u_sub:
                Rc, tc = refine_pose(pn, res.rotation, res.translation)
                if pn.cost(Rc, tc) < best_u:
                    best_R, best_t, best_u = Rc, tc, pn.cost(Rc, tc)
        else:
            # Too many nodes (a large clique with many near-threshold terms): the joint dual
            # search bounds the clique subproblem instead.
            remaining = budget - (time.perf_counter() - t0)
            if C.size > JOINT_DUAL_MAX:
                methods.add(f"bnb stopped at {res.nodes} nodes on {C.size} terms")
                stopped = True
                lower = min(lower, floor + out_cost)
                continue
            methods.add("joint_dual")
            if remaining <= 0:
                stopped = True
                lower = min(lower, floor + out_cost)
                continue
            Rc, tc = refine_pose(sub, R, t)
            b = _joint_drs_bound(sub, Rc, tc, tol / 4, max_iter or 3000, remaining)
            lb_sub = b.lower if b.accepted else 0.0
            if b.status is CertificateStatus.ITERATION_LIMIT:
                stopped = True
        lower = min(lower, max(lb_sub, floor) + out_cost)
    if undiluted_gap(u, lower, _outlier_cost(pn, R, t)) > tol:  # the cliques leave a gap
        shared, _ = _shared_source(pn)
        if shared.lower > lower:
            methods.add("shared-source bound")
            lower = shared.lower
    lower = min(lower, u)  # the bound never exceeds a pose's cost
    rot, trans = (best_R, best_t) if best_R is not None else (None, None)
    return _Bound(
        lower=float(lower), accepted=True,
        status=CertificateStatus.ITERATION_LIMIT if stopped else CertificateStatus.GAP_TOO_LARGE,
        backend_status=f"cliques:{len(cliques)} bounded ({'+'.join(sorted(methods)) or 'none'}"
                       f", {sum(iters)} nodes)",
        eigenvalue_ratio=np.nan, method="clique_decomposition",
        message=(f"clique decomposition over {len(cliques)} maximal clique(s) of sizes "
                 f"{[int(c.size) for c in cliques][:8]}: {'; '.join(sorted(methods)) or 'none'}"
                 + ("; stopped before every clique was bounded exactly" if stopped else "")),
        rotation=rot, translation=trans, cliques=tuple(used),
    )


def _pose_search_bound(pn: WeightedTLSProblem, R: NDArray[np.float64], t: NDArray[np.float64],
                       *, tol: float, time_limit: float | None, t0: float, share: float
                       ) -> _Bound:
    """The branch and bound over poses as a :class:`_Bound` (``GAP_TOO_LARGE`` when it
    completed at ``tol``: the verdict then rests on the gap; else ``ITERATION_LIMIT`` with the
    last gap it proved)."""
    from solvers.certify.pose_bnb import pose_lower_bound

    budget = POSE_DEFAULT_TIME if time_limit is None else time_limit * share
    budget = max(budget - (time.perf_counter() - t0), 0.0)
    res = pose_lower_bound(pn, R, t, tol=tol, time_limit=budget, refine=refine_pose)
    stages = ", ".join(f"{g:g} {'proved' if ok else 'stopped'} ({n} cells, {s:.2f} s)"
                       for g, ok, n, s in res.stages)
    proved = [g for g, ok, _, _ in res.stages if ok]
    return _Bound(
        lower=res.lower, accepted=True,
        status=CertificateStatus.GAP_TOO_LARGE if res.complete else CertificateStatus.ITERATION_LIMIT,
        backend_status=f"pose_bnb: {stages or 'no stage run'}", eigenvalue_ratio=np.nan,
        method="pose_bnb",
        message=("too many maximal cliques to list; bounded by a branch and bound over poses "
                 "(rotation x translation cells, per-term, colouring and joint convex bounds, exact "
                 "inlier sets in small cells)" + (f": gap {min(proved):g} proved" if proved else
                                           ": no stage completed within the time limit")
                 + ("" if res.complete else f", gap {tol:g} not reached within the time limit")),
        rotation=res.rotation, translation=res.translation)


# ----------------------------------------------------------------------------- certificates
def _finish_certificate(
    upper: float, bound: _Bound, *, tol: float, scoped: _Scoped, ws: float, outlier_cost: float,
    t0: float, better: float | None = None,
) -> Certificate:
    """The certificate of a pose of cost ``upper`` (user units); ``bound`` is normalised."""
    u, lo, c = upper / ws, bound.lower, outlier_cost / ws
    gap = undiluted_gap(u, lo, c)
    lit = relative_gap(u, lo)
    status = bound.status
    if bound.accepted and np.isfinite(lo) and lo > u + 1e-9 * (1 + abs(u)):
        # A lower bound above a feasible cost: the numbers cannot be trusted.
        certified, status = False, CertificateStatus.SOLVER_ERROR
        msg = (f"no certificate: the lower bound {lo:.9g} exceeds the pose's cost {u:.9g} "
               f"(numerical failure)")
    else:
        certified = bool(bound.accepted and gap <= tol)
        if certified:
            status = CertificateStatus.CERTIFIED
            msg = (f"globally optimal for {scoped.label.value} within gap {gap:.3g} <= {tol:g}")
        elif bound.status is CertificateStatus.GAP_TOO_LARGE or (
            bound.accepted and bound.status is CertificateStatus.ITERATION_LIMIT
        ):
            msg = (f"gap {gap:.3g} > {tol:g}: the pose is suboptimal or the bound is not tight "
                   f"({bound.message})")
        else:
            msg = f"no certificate: {bound.message}"
    if better is not None:
        opt = bound.accepted and relative_gap(better / ws, lo) <= tol
        msg += (f"; the candidate is suboptimal: a pose of cost {better:.6g} (vs {upper:.6g}) on "
                f"the {scoped.label.value} was found"
                + (", globally optimal within the tolerance" if opt else ""))
    return Certificate(
        upper_bound=float(upper),
        lower_bound=float(lo * ws) if np.isfinite(lo) else float(lo),
        relative_gap=float(gap),
        certified=certified,
        tol=tol,
        problem=scoped.label.value,
        eigenvalue_ratio=float(bound.eigenvalue_ratio),
        backend_status=bound.backend_status,
        solve_time=time.perf_counter() - t0,
        message=msg,
        status=status,
        method=bound.method,
        num_terms=int(scoped.problem.n),
        literature_gap=float(lit),
        weight_scale=float(ws),
        outlier_cost=float(outlier_cost),
        indices=None if scoped.indices is None else tuple(int(i) for i in scoped.indices),
        pairs=None if scoped.pairs is None else tuple((int(i), int(j)) for i, j in scoped.pairs),
        cliques=bound.cliques,
        better_upper_bound=None if better is None else float(better),
    )


def _invalid(upper: float, why: str, tol: float, problem: BoundedProblem, t0: float) -> Certificate:
    return Certificate(
        upper_bound=float(upper), lower_bound=-np.inf, relative_gap=np.inf, certified=False,
        tol=tol, problem=problem.value, eigenvalue_ratio=np.nan, backend_status="not_run",
        solve_time=time.perf_counter() - t0, message=f"no certificate: {why}",
        status=CertificateStatus.INVALID_INPUT, method="", num_terms=0,
        literature_gap=np.inf,
    )


def _max_bound(a: _Bound, b: _Bound | None) -> _Bound:
    """The better of two valid bounds of the same problem."""
    if b is None or not b.accepted:
        return a
    if not a.accepted or b.lower > a.lower:
        return dataclasses.replace(b, rotation=a.rotation if b.rotation is None else b.rotation)
    return a


def _certify(
    problem: WeightedTLSProblem,
    R: NDArray[np.float64],
    t: NDArray[np.float64],
    *,
    tol: float,
    scope: Scope,
    method: Method,
    survivors: ArrayLike | None,
    max_iter: int | None,
    time_limit: float | None,
    dense_max: int | None,
    eps: float,
    extra: _Bound | None = None,
    skip_futile: bool = False,
    known: _Bound | None = None,
    pose_search: bool = False,
) -> tuple[Certificate, tuple[NDArray[np.float64], NDArray[np.float64]] | None, _Bound]:
    """Certificate of ``(R, t)``, a better pose of the bounded problem if one was found, and
    the bound used.

    ``extra`` is an already computed bound on the *normalised* bounded problem (e.g. from the
    relaxation ``solve_sdp`` rounded); ``skip_futile`` and ``pose_search`` as in
    :func:`certify_result`. ``known``:
    a bound of the same rotation subproblem computed for another candidate (it holds for
    every rotation), used instead of a new search.
    """
    t0 = time.perf_counter()
    scoped = _scope_problem(problem, scope, survivors)
    bp = scoped.problem
    pn, ws = _normalised(bp)
    upper = _cost(bp, R, t)
    c_out = _outlier_cost(bp, R, t)
    better: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
    if isinstance(pn, RotationTLSProblem):
        # The candidate optimised the full problem; the dual search starts from the best
        # rotation at hand (a dual certificate exists only at an optimum), the bound holds
        # whatever built it.
        if known is not None:
            Rd, bound = R, known
        else:
            Rd = _dual_candidate(pn, R)
            bound = _rotation_bound(pn, Rd, method=method, tol=tol, max_iter=max_iter,
                                    time_limit=time_limit, dense_max=dense_max or 10, eps=eps,
                                    outlier_cost=c_out / ws)
        bound = _max_bound(bound, extra)
        cands = [Rd] + ([bound.rotation] if bound.rotation is not None else [])
        Ra = _round_rotation(bound.Z00)
        if Ra is not None:
            cands.append(refine_rotation(pn, Ra))
        Rb = min(cands, key=pn.cost)
        if pn.cost(Rb) < pn.cost(R) - 1e-9 * max(1.0, pn.cost(R)):
            idx = scoped.indices if scoped.indices is not None else np.arange(problem.n)
            better = (Rb, _vote_translation(problem, Rb, idx))
    else:
        dmax = dense_max or 4
        if scoped.label is BoundedProblem.FULL and method == "auto":
            bound = _clique_bound(pn, R, t, tol=tol, max_iter=max_iter, time_limit=time_limit,
                                  eps=eps, skip_futile=skip_futile, pose_search=pose_search)
        else:
            bound = _joint_bound(pn, R, t, method=method, tol=tol, max_iter=max_iter,
                                 time_limit=time_limit, dense_max=dmax, eps=eps,
                                 outlier_cost=c_out / ws)
        bound = _max_bound(bound, extra)
        cands = []
        if bound.rotation is not None and bound.translation is not None:
            cands.append((bound.rotation, bound.translation))
        if bound.Z00 is not None:
            _, V = np.linalg.eigh((bound.Z00 + bound.Z00.T) / 2)
            Ra, ta = joint_lifting(pn).pose_from_vector(V[:, -1])
            cands.append(refine_pose(pn, Ra, ta))
        u0 = pn.cost(R, t)
        for Rb, tb in cands:
            if pn.cost(Rb, tb) < u0 - 1e-9 * max(1.0, u0) and (
                better is None or pn.cost(Rb, tb) < pn.cost(*better)
            ):
                better = (Rb, tb)
        if better is not None and scoped.indices is not None:
            better = refine_pose(problem, *better)  # a pruned pose, refined on the user's problem
    better_cost = None if better is None else _cost(bp, better[0], better[1])
    if better_cost is not None and not better_cost < upper:
        better, better_cost = None, None
    cert = _finish_certificate(upper, bound, tol=tol, scoped=scoped, ws=ws, outlier_cost=c_out,
                               t0=t0, better=better_cost)
    return cert, better, bound


# ----------------------------------------------------------------------------- public API
def certify_rotation(
    problem: RotationTLSProblem,
    R: ArrayLike,
    *,
    tol: float = 1e-3,
    method: Method = "auto",
    max_iter: int | None = None,
    time_limit: float | None = None,
    dense_max: int = 10,
    eps: float = 1e-7,
) -> Certificate:
    """Certify a rotation for a rotation-only TLS problem (QUASAR relaxation).

    Parameters
    ----------
    problem : RotationTLSProblem
    R : (3, 3) array_like
        Candidate rotation (orthonormal with determinant 1 within ``ROTATION_ATOL``).
    tol : float
        Tolerance on the gap (see :class:`~solvers.certificate.Certificate`).
    method : {"auto", "dense", "chordal", "dual"}
        ``"dense"``: interior-point solve of the relaxation with all redundant constraints;
        ``"chordal"``: clique-decomposed relaxation (looser); ``"dual"``: Douglas-Rachford search
        of a dual certificate for ``R``. ``"auto"``: the dual search, then, if it did not
        converge and ``K <= dense_max``, the dense interior point.
    max_iter : int or None
        Backend iteration limit (Clarabel: 200; Douglas-Rachford: 500, where a certificate of
        the optimum takes 2-10).
    time_limit : float or None
        Seconds for the dual search (default ``DEFAULT_DUAL_TIME_LIMIT`` = 120 s) and Clarabel's
        time limit (default none).
    dense_max : int
        Largest ``K`` for the dense interior-point solve under ``"auto"``.
    eps : float
        Clarabel's tolerances.
    """
    t0 = time.perf_counter()
    tol = _check_tol(tol)
    _check_options(method, max_iter, time_limit, dense_max, eps)
    R, _, why = _candidate_error(R, np.zeros(3))
    scoped = _Scoped(BoundedProblem.ROTATION, problem, None, None)
    if why:
        return _invalid(np.nan, why, tol, BoundedProblem.ROTATION, t0)
    pn, ws = _normalised(problem)
    upper = problem.cost(R)
    Rd = _dual_candidate(pn, R)
    c_out = _outlier_cost(problem, R, None)
    bound = _rotation_bound(pn, Rd, method=method, tol=tol, max_iter=max_iter,
                            time_limit=time_limit, dense_max=dense_max, eps=eps,
                            outlier_cost=c_out / ws)
    cands = [Rd] + ([bound.rotation] if bound.rotation is not None else [])
    Rb = min(cands, key=pn.cost)
    better = problem.cost(Rb) if pn.cost(Rb) < pn.cost(R) - 1e-9 * max(1.0, pn.cost(R)) else None
    return _finish_certificate(upper, bound, tol=tol, scoped=scoped, ws=ws,
                               outlier_cost=c_out, t0=t0, better=better)


def _check_options(method: str, max_iter: Any = None, time_limit: Any = None,
                   dense_max: Any = None, eps: Any = 1e-7) -> None:
    """One-line errors naming the argument (non-integer counts, negative or NaN limits)."""
    from solvers.validation import check_count, check_limit

    if method not in ("auto", "dense", "chordal", "dual"):
        raise ValueError(f"`method` must be 'auto', 'dense', 'chordal' or 'dual', got {method!r}.")
    if max_iter is not None:
        check_count(max_iter, "max_iter", minimum=1)
    if dense_max is not None:
        check_count(dense_max, "dense_max", minimum=1)
    check_limit(time_limit, "time_limit")
    if not check_limit(eps, "eps", allow_none=False) > 0:
        raise ValueError(f"`eps` must be positive, got {eps!r}.")


def certify_pose(
    problem: WeightedTLSProblem | RotationTLSProblem,
    R: ArrayLike,
    t: ArrayLike | None = None,
    *,
    tol: float = 1e-3,
    scope: Scope = "auto",
    method: Method = "auto",
    survivors: ArrayLike | None = None,
    max_iter: int | None = None,
    time_limit: float | None = None,
    dense_max: int | None = None,
    eps: float = 1e-7,
) -> Certificate:
    """Certify (or refuse) a candidate pose; the certificate says which problem it bounds.

    Parameters
    ----------
    problem : WeightedTLSProblem or RotationTLSProblem
    R : (3, 3) array_like
        Candidate rotation (orthonormal with determinant 1 within ``ROTATION_ATOL``).
    t : (3,) array_like or None
        Candidate translation (units of the points); ignored for rotation problems.
    tol : float
        Tolerance on the gap (default 1e-3; see :class:`~solvers.certificate.Certificate`).
    scope : {"auto", "full", "pruned", "rotation"}
        Which problem to bound (see the module docstring); ``"auto"`` is ``"full"``.
    method : {"auto", "dense", "chordal", "dual"}
        Relaxation and solver. ``"auto"``: for rotation problems the dual certificate search
        with the dense interior point as fallback for ``K <= dense_max``; for the full problem
        clique decomposition (exact branch and bound per clique, the joint dual search for
        cliques beyond its node budget); for the pruned one the dense joint relaxation for
        ``K <= dense_max``, else its dual search. ``"dense"``/``"chordal"``/``"dual"`` on the
        full problem bound it as a whole with that relaxation.
    survivors : array_like of int or None
        Max-clique survivors, if already known (else recomputed for ``"pruned"``/``"rotation"``).
    max_iter, time_limit, eps
        Backend limits and tolerances (``time_limit`` in seconds, default 120 s per search).
    dense_max : int or None
        Default 10 for rotation problems, 4 for full/pruned ones.

    Returns
    -------
    Certificate
        Attached to exactly ``(R, t)``: ``upper_bound`` is its cost on the bounded problem.
        Never raises on a backend failure; ``certified`` is False with a ``status`` then.

    Raises
    ------
    ValueError
        Wrong shapes of ``R``/``t`` or bad options.
    """
    t0 = time.perf_counter()
    tol = _check_tol(tol)
    _check_options(method, max_iter, time_limit, dense_max, eps)
    if isinstance(problem, RotationTLSProblem):
        return certify_rotation(problem, R, tol=tol, method=method, max_iter=max_iter,
                                time_limit=time_limit, dense_max=dense_max or 10, eps=eps)
    if not isinstance(problem, WeightedTLSProblem):
        raise TypeError(f"`problem` must be a WeightedTLSProblem, got {type(problem).__name__}.")
    if t is None:
        raise ValueError("`t` is required for a WeightedTLSProblem.")
    R, t, why = _candidate_error(R, t)
    scoped = _scope_problem(problem, scope, survivors)
    if why:
        return _invalid(np.nan, why, tol, scoped.label, t0)
    cert, _, _ = _certify(problem, R, t, tol=tol, scope=scope, method=method, survivors=survivors,
                       max_iter=max_iter, time_limit=time_limit, dense_max=dense_max, eps=eps)
    return dataclasses.replace(cert, solve_time=time.perf_counter() - t0)


def _round_rotation(Z00: NDArray[np.float64] | None) -> NDArray[np.float64] | None:
    from solvers.certify.relaxation import quaternion_to_rotation

    if Z00 is None:
        return None
    _, V = np.linalg.eigh((Z00 + Z00.T) / 2)
    return quaternion_to_rotation(V[:, -1])


def _vote_translation(
    problem: WeightedTLSProblem, R: NDArray[np.float64], idx: NDArray[np.int64]
) -> NDArray[np.float64]:
    from solvers.registration.pruning import vote_translation

    return vote_translation(problem, R, idx)


def solve_sdp(
    problem: WeightedTLSProblem,
    *,
    tol: float = 1e-3,
    scope: Scope = "rotation",
    method: Method = "auto",
    max_iter: int | None = None,
    time_limit: float | None = None,
    dense_max: int | None = None,
    eps: float = 1e-7,
) -> RegistrationResult:
    """Solve a weighted TLS problem through its SDP relaxation, with a certificate.

    The relaxation's moment matrix is rounded (leading eigenvector, projection to SO(3)) and
    refined locally on the bounded problem. With ``scope="rotation"`` (the default, what TEASER++
    solves) the rotation is the TIM rotation subproblem's (over the max-clique survivors) and the
    translation comes from exact per-axis TLS voting; it is not refined on the full problem,
    which would leave the certified optimum (``info["refined_full_cost"]`` says what refining
    would reach; :func:`certify_result` of a GNC pose gives the full problem's certificate).
    With ``scope="full"``/``"pruned"`` the joint relaxation gives the whole pose (``K <=
    dense_max`` densely, else the loose chordal relaxation), refined on the full problem. The
    certificate is computed for the *returned* pose on the bounded problem; the relaxation's own
    bound is one of its lower bounds.

    Parameters
    ----------
    problem : WeightedTLSProblem
    tol, scope, method, max_iter, time_limit, dense_max, eps
        As in :func:`certify_pose` (``"auto"`` scope: ``"rotation"`` here).

    Returns
    -------
    RegistrationResult
        ``solver="sdp"``, with the certificate in ``.certificate``. A failed backend gives
        ``status=SOLVER_ERROR`` (never an exception).
    """
    from solvers.registration.solve import _finish

    t0 = time.perf_counter()
    tol = _check_tol(tol)
    _check_options(method, max_iter, time_limit, dense_max, eps)
    scope = "rotation" if scope == "auto" else scope
    scoped = _scope_problem(problem, scope, None)
    pn, _ = _normalised(scoped.problem)
    info: dict[str, Any] = {"bounded_problem": scoped.label.value}
    rot = isinstance(pn, RotationTLSProblem)
    dmax = dense_max or (10 if rot else 4)
    kind = method if method in ("dense", "chordal") else ("dense" if pn.n <= dmax else "chordal")
    lift = rotation_lifting(pn) if rot else joint_lifting(pn)
    sol = _ipm_bound(lift, kind, max_iter or 200, eps, time_limit)
    if sol.Z00 is None:
        res = _finish(problem, np.eye(3), np.zeros(3), iterations=0, t0=t0,
                      status=SolverStatus.SOLVER_ERROR,
                      message=f"SDP relaxation failed: {sol.message}", solver="sdp", info=info)
        cert = _invalid(np.nan, f"the relaxation failed ({sol.message})", tol, scoped.label, t0)
        return dataclasses.replace(res, certificate=dataclasses.replace(
            cert, status=sol.status, backend_status=sol.backend_status, method=sol.method))
    _, V = np.linalg.eigh((sol.Z00 + sol.Z00.T) / 2)
    if rot:
        # TEASER++'s pose: the subproblem's rotation, translation voted exactly. Refining it on
        # the full problem would leave the subproblem's optimum, which is what is certified.
        R = refine_rotation(pn, _round_rotation(sol.Z00))
        idx = scoped.indices if scoped.indices is not None else np.arange(problem.n)
        t = _vote_translation(problem, R, idx)
        Rr, tr = refine_pose(problem, R, t)
        info["refined_full_cost"] = problem.cost(Rr, tr)
    else:
        R, t = lift.pose_from_vector(V[:, -1])
        R, t = refine_pose(problem, *refine_pose(pn, R, t))
    # The certificate is for the pose returned; the relaxation's bound is one of its bounds.
    cert, _, _ = _certify(problem, R, t, tol=tol, scope=scope, method="dual" if rot else method,
                       survivors=scoped.indices, max_iter=None, time_limit=time_limit,
                       dense_max=dmax, eps=eps, extra=sol if sol.accepted else None)
    status = SolverStatus.CONVERGED if sol.accepted else SolverStatus.SOLVER_ERROR
    msg = (f"SDP ({sol.method}) rounded and refined; {cert.summary()}" if sol.accepted
           else f"SDP backend did not reach its tolerances ({sol.message}); pose is the rounded "
                f"estimate")
    res = _finish(problem, R, t, iterations=0, t0=t0, status=status, message=msg, solver="sdp",
                  info=info)
    return dataclasses.replace(res, certificate=cert)


def certify_result(
    problem: WeightedTLSProblem,
    result: RegistrationResult,
    *,
    tol: float = 1e-3,
    scope: Scope = "auto",
    method: Method = "auto",
    survivors: ArrayLike | None = None,
    max_iter: int | None = None,
    time_limit: float | None = None,
    dense_max: int | None = None,
    eps: float = 1e-7,
    skip_futile: bool = False,
    rotation_fallback: bool = False,
    prefer_certified: bool = False,
    pose_search: bool = False,
) -> RegistrationResult:
    """Attach a certificate to ``result``'s pose, or to a better pose found while certifying.

    The returned pose is the best found *for the problem the user posed*: when certifying finds
    a better optimum of the bounded problem, its pose (refined on ``problem``) replaces the
    candidate only if its cost on ``problem`` is not higher, and is then certified itself
    (``status=SolverStatus.CERTIFIER_POSE``, ``info["replaced_candidate"] = True``, the
    candidate's status, cost and certificate in ``info``). Otherwise the candidate keeps its certificate, which
    records the better subproblem cost (``better_upper_bound``, also in
    ``info["better_subproblem_cost"]``). Either way the certificate's ``upper_bound`` is the
    returned pose's cost on the bounded problem.

    Parameters
    ----------
    problem : WeightedTLSProblem
        The problem ``result`` was computed for.
    result : RegistrationResult
    tol, scope, method, survivors, max_iter, time_limit, dense_max, eps
        As in :func:`certify_pose` (``scope="auto"`` is the full problem). ``time_limit``
        covers the whole call: a better pose is certified in what is left of it.
    skip_futile : bool
        For callers who want a certificate rather than a bound: a fallback bound that cannot
        certify the pose whatever it finds is not searched (on the full problem, the clique
        number when the maximal cliques are too many to list: the certificate then says "not
        attempted" and bounds by 0). Measured on YCB-Video's eq. (2) problems (233-474 terms,
        clique-number bound's best possible gap 0.99), it saves the 0.01-0.4 s that search took.
    rotation_fallback : bool
        With ``scope="auto"``: when the full problem's bound gives up (real-feature scans: too
        many maximal cliques to bound; status ``ITERATION_LIMIT``), certify the rotation
        subproblem over the max clique's
        translation-invariant measurements (what TEASER++ certifies), in what is left of
        ``time_limit``. When its certified optimum, with the translation refined on
        ``problem``, costs no more on ``problem`` than the candidate, that pose is returned
        (``CERTIFIER_POSE``). The returned certificate is the rotation subproblem's when it
        certifies the returned pose (the full problem's then in
        ``info["full_problem_certificate"]``), else the full problem's (the rotation
        subproblem's in ``info["rotation_certificate"]``); ``certificate.problem`` says which.
        The full problem's futile clique-number search is skipped (as ``skip_futile``).
    prefer_certified : bool
        With ``rotation_fallback``: return the rotation subproblem's certified optimum (its
        translation refined on ``problem``; TEASER++'s kind of pose) even when it costs more on
        ``problem`` than the candidate, which is then described in ``info`` (``candidate_cost``,
        ``candidate_T_target_source``). Measured on a real 3DMatch pair (940 FPFH
        correspondences): +0.97 and +1.96 on costs of 908 and 870 (noise bounds 0.05 and 0.1),
        about one correspondence's outlier cost. Without it, the subproblem's dual search is
        skipped when it could only refuse the candidate (:func:`_futile_rotation_certificate`).
    pose_search : bool
        On the full problem, when the maximal cliques are too many to list (real-feature
        scans), bound it by a branch and bound over poses (:mod:`solvers.certify.pose_bnb`)
        rather than by the clique number alone: it raises its threshold through a sequence of
        gaps (0.3, 0.1, 0.07, ..., ``tol``) while time remains (``POSE_DEFAULT_TIME`` seconds
        without a limit), keeping the cells each stage leaves, so its bound (the least bound
        of those cells) rises until the time limit, even within a stage. With ``rotation_fallback`` it runs after the subproblem's certificate, in what
        that leaves, for the returned pose: its certificate replaces the subproblem's when it
        certifies, else it is recorded as ``info["full_problem_certificate"]`` (a better pose
        it finds: its cost as ``info["full_problem_better_cost"]``). When the returned pose is
        the subproblem's and costs more than the best pose the search holds (the solver's, or
        one it found) and the search certifies that pose, it is returned instead
        (``CERTIFIER_POSE``; the subproblem's certificate, pose and cost in ``info`` as
        ``rotation_certificate``, ``subproblem_T_target_source``, ``subproblem_cost``): a
        certified optimum of the problem posed. Without it, a better pose it finds is returned
        as the certifier's.
    """
    t0 = time.perf_counter()
    tol = _check_tol(tol)
    _check_options(method, max_iter, time_limit, dense_max, eps)
    R, t = np.array(result.rotation), np.array(result.translation)
    scoped = _scope_problem(problem, scope, survivors)
    _, _, why = _candidate_error(R, t)
    if why:
        return dataclasses.replace(result, certificate=_invalid(np.nan, why, tol, scoped.label, t0))
    kw: dict[str, Any] = dict(tol=tol, scope=scope, method=method, survivors=scoped.indices,
                              max_iter=max_iter, time_limit=time_limit, dense_max=dense_max,
                              eps=eps, skip_futile=bool(skip_futile),
                              pose_search=bool(pose_search))
    fallback = bool(rotation_fallback) and scope in ("auto", "full")
    if fallback:
        # The subproblem's certificate comes first; the pose search gets what it leaves.
        kw.update(skip_futile=True, pose_search=False)
    out = _certify_once(problem, result, kw, scoped, t0)
    # Only when the full problem's bound gave up (not when it is tight and the pose is not
    # optimal: that statement is the stronger one).
    gave_up = out.certificate.status in (CertificateStatus.ITERATION_LIMIT,
                                         CertificateStatus.INACCURATE,
                                         CertificateStatus.SOLVER_ERROR)
    if not fallback or not gave_up:
        return out
    out = _rotation_fallback(problem, out, kw, t0, prefer_certified=bool(prefer_certified))
    if pose_search:
        out = _full_after_fallback(problem, out, kw, t0)
    return out


def _full_after_fallback(problem: WeightedTLSProblem, out: RegistrationResult,
                         kw: dict[str, Any], t0: float) -> RegistrationResult:
    """The full problem bounded by the pose search for ``out``'s pose in what is left of the
    time limit (the search starts from the solver's pose when ``info`` holds it as a cheaper
    candidate). When ``out``'s certificate is the rotation subproblem's, the new one replaces
    it if it certifies, else it is recorded in ``info`` if it proves a smaller gap than the one
    there; when it is the full problem's (the subproblem certified nothing), the new one
    replaces it if its gap is smaller."""
    remaining = _remaining(kw, t0)
    if remaining is not None and remaining <= 0:
        return out
    t1 = time.perf_counter()
    R, t = np.array(out.rotation), np.array(out.translation)
    scoped = _scope_problem(problem, "full", None)
    pn, ws = _normalised(problem)
    # The listing already gave up on this problem: straight to the pose search, from the
    # best pose at hand (a lower first threshold: fewer cells to search).
    Rs, ts = R, t
    cand = out.info.get("candidate_T_target_source")
    if cand is not None:
        T = np.asarray(cand, dtype=np.float64)
        if problem.cost(T[:3, :3], T[:3, 3]) < problem.cost(R, t):
            Rs, ts = T[:3, :3], T[:3, 3]
    bound = _pose_search_bound(pn, Rs, ts, tol=kw["tol"], t0=t1, share=1.0,
                               time_limit=POSE_DEFAULT_TIME if remaining is None else remaining)
    better = None
    if bound.rotation is not None and bound.translation is not None:
        Rs, ts = bound.rotation, bound.translation
    if Rs is not R:  # the search's best pose: one it found, or the cheaper one it started from
        better = problem.cost(Rs, ts)
        better = better if better < problem.cost(R, t) else None
    cert = _finish_certificate(problem.cost(R, t), bound, tol=kw["tol"], scoped=scoped, ws=ws,
                               outlier_cost=_outlier_cost(problem, R, t), t0=t1, better=better)
    info = dict(out.info)
    if better is not None:
        info["full_problem_better_cost"] = better
    full = out.certificate.problem == BoundedProblem.FULL.value
    if better is not None:
        won = _cheaper_pose(problem, out, (Rs, ts), bound, better, info, tol=kw["tol"],
                            scoped=scoped, ws=ws, t0=t0, t1=t1, need_certificate=not full)
        if won is not None:
            return won
    if full:
        if not (cert.certified or cert.relative_gap < out.certificate.relative_gap):
            return dataclasses.replace(out, info=info)
        return dataclasses.replace(out, certificate=dataclasses.replace(
            cert, solve_time=time.perf_counter() - t0), info=info,
            message=f"{out.message}; the full problem bounded by the pose search: "
                    f"{cert.message}")
    if cert.certified:
        info["rotation_certificate"] = out.certificate.to_dict()
        info.pop("full_problem_certificate", None)
        return dataclasses.replace(out, certificate=dataclasses.replace(
            cert, solve_time=time.perf_counter() - t0), info=info,
            message=f"{out.message}; the full problem certified by the pose search")
    old = info.get("full_problem_certificate")
    if old is None or cert.relative_gap < (old.get("relative_gap") or np.inf):
        info["full_problem_certificate"] = cert.to_dict()
    return dataclasses.replace(out, info=info)


def _cheaper_pose(problem: WeightedTLSProblem, out: RegistrationResult,
                  pose: tuple[NDArray[np.float64], NDArray[np.float64]], bound: _Bound,
                  better: float, info: dict[str, Any], *, tol: float, scoped: _Scoped,
                  ws: float, t0: float, t1: float, need_certificate: bool
                  ) -> RegistrationResult | None:
    """The pose search's best ``pose`` (cost ``better``, below ``out``'s) with its full-problem
    certificate, in place of ``out``; ``None`` when ``need_certificate`` and it is not
    certified.

    ``out`` holding the rotation subproblem's certificate (``need_certificate``): a certified
    optimum of the problem posed is the stronger statement, and the subproblem's certificate,
    pose and cost are recorded in ``info``. ``out`` holding the full problem's: the cheaper
    pose has the smaller gap, certified or not, and ``out`` is recorded as the candidate.
    """
    Rb, tb = np.array(pose[0]), np.array(pose[1])
    cert = _finish_certificate(better, bound, tol=tol, scoped=scoped, ws=ws,
                               outlier_cost=_outlier_cost(problem, Rb, tb), t0=t1)
    if need_certificate and not cert.certified:
        return None
    old = problem.cost(out.rotation, out.translation)
    info = dict(info, replaced_candidate=True)
    info.pop("full_problem_certificate", None)
    if need_certificate:
        info.update(rotation_certificate=out.certificate.to_dict(), subproblem_cost=old,
                    subproblem_T_target_source=out.T_target_source.tolist())
        what = (f"the full problem's pose search certified a cheaper pose (cost {better:.6g} < "
                f"{old:.6g}, the rotation subproblem's certified pose) globally optimal; "
                "returning it")
    else:
        for key, value in (("candidate_cost", old), ("candidate_status", out.status.value),
                           ("candidate_certificate", out.certificate.to_dict()),
                           ("candidate_T_target_source", out.T_target_source.tolist())):
            info.setdefault(key, value)
        what = (f"the full problem's pose search found a cheaper pose (cost {better:.6g} < "
                f"{old:.6g}); returning it with its certificate")
    return _with_pose(problem, out, Rb, tb, better, cert, info, what, t0, before="Before")


def _remaining(kw: dict[str, Any], t0: float) -> float | None:
    limit = kw["time_limit"]
    return None if limit is None else max(float(limit) - (time.perf_counter() - t0), 0.0)


def _rotation_fallback(problem: WeightedTLSProblem, out: RegistrationResult,
                       kw: dict[str, Any], t0: float, *, prefer_certified: bool
                       ) -> RegistrationResult:
    """``certify_result``'s ``rotation_fallback`` for ``out`` (its full-problem certificate
    did not certify): the rotation subproblem's certificate, of ``out``'s pose or of the
    subproblem's optimum when that is no worse on ``problem``."""
    full = out.certificate
    t1 = time.perf_counter()
    scoped = _scope_problem(problem, "rotation", None)
    if not prefer_certified:
        futile = _futile_rotation_certificate(problem, out, scoped, kw["tol"], t1)
        if futile is not None:
            info = dict(out.info, rotation_certificate=futile.to_dict())
            return dataclasses.replace(out, info=info, certificate=dataclasses.replace(
                full, solve_time=time.perf_counter() - t0),
                message=f"{out.message}; rotation subproblem: {futile.message}")
    rkw = dict(kw, scope="rotation", survivors=scoped.indices, skip_futile=False,
               time_limit=_remaining(kw, t0))
    rot = _certify_once(problem, out, rkw, scoped, t1, accept_worse=prefer_certified)
    info = dict(rot.info)
    same = np.array_equal(rot.T_target_source, out.T_target_source)
    if rot.certificate.certified:
        info["full_problem_certificate"] = full.to_dict()
        msg = (f"{rot.message}; " + ("" if same else "its rotation ")
               + f"certified on the rotation subproblem; the full problem is not certified "
               f"({full.message})")
        return dataclasses.replace(rot, info=info, message=msg, certificate=dataclasses.replace(
            rot.certificate, solve_time=time.perf_counter() - t0))
    # Not certified on the subproblem either: the full problem's certificate is of ``out``'s
    # pose, which is kept; the subproblem's bound is recorded (of the pose it was computed for).
    rc = rot.certificate.to_dict()
    rc["pose_T_target_source"] = rot.T_target_source.tolist()
    info = dict(out.info, rotation_certificate=rc)
    return dataclasses.replace(out, info=info, certificate=dataclasses.replace(
        full, solve_time=time.perf_counter() - t0),
        message=f"{out.message}; rotation subproblem: {rot.certificate.message}")


def _futile_rotation_certificate(problem: WeightedTLSProblem, out: RegistrationResult,
                                 scoped: _Scoped, tol: float, t0: float) -> Certificate | None:
    """The rotation subproblem's certificate of ``out``'s pose when searching for it is futile
    for a caller who keeps the cheaper pose (``prefer_certified=False``), else ``None``.

    It is futile when the subproblem's local solvers (:func:`_dual_candidate`: GNC, refinement)
    already find a rotation of lower subproblem cost than the candidate's, so no certificate of
    the candidate's rotation exists, and that rotation's pose (translation voted and refined)
    costs more on the full problem, so it would not be returned either. The dual search would
    then spend its time (measured on TEASER++'s ``cloud_bin_0 -> 4`` example at 0.05 m, 107
    terms: 340-364 iterations, 5.7 s) only to refuse the candidate; the full problem's pose
    search gets that time instead. The certificate returned bounds the subproblem by 0 (TLS
    costs are non-negative) and names the better rotation's cost: sound, not certified.
    """
    pn, ws = _normalised(scoped.problem)
    R, t = np.array(out.rotation), np.array(out.translation)
    Rd = _dual_candidate(pn, R)
    f = pn.cost(R)
    if not pn.cost(Rd) < f - 1e-9 * max(1.0, f):
        return None
    idx = scoped.indices if scoped.indices is not None else np.arange(problem.n)
    tb = min((refine_translation(problem, Rd, tt) for tt in (_vote_translation(problem, Rd, idx), t)),
             key=lambda tt: problem.cost(Rd, tt))
    if not problem.cost(Rd, tb) > problem.cost(R, t):
        return None
    bound = _Bound(lower=0.0, accepted=True, status=CertificateStatus.GAP_TOO_LARGE,
                   backend_status="not attempted", eigenvalue_ratio=np.nan, method="none",
                   message="dual search not attempted: the local solvers found a better rotation "
                           f"of the subproblem, whose pose costs more on the full problem "
                           f"({problem.cost(Rd, tb):.6g} > {problem.cost(R, t):.6g}); bounded "
                           "by 0")
    bp = scoped.problem
    return _finish_certificate(_cost(bp, R, t), bound, tol=tol, scoped=scoped, ws=ws,
                               outlier_cost=_outlier_cost(bp, R, t), t0=t0,
                               better=pn.cost(Rd) * ws)


def _certify_once(problem: WeightedTLSProblem, result: RegistrationResult, kw: dict[str, Any],
                  scoped: _Scoped, t0: float, *, accept_worse: bool = False) -> RegistrationResult:
    """``certify_result`` on one bounded problem (``kw``: :func:`_certify`'s options);
    ``accept_worse``: a better pose of the bounded problem replaces the candidate even when it
    costs more on ``problem``, if it is then certified."""
    R, t = np.array(result.rotation), np.array(result.translation)
    time_limit = kw["time_limit"]
    cert, better, bound = _certify(problem, R, t, **kw)
    info = dict(result.info)
    if better is None:
        return dataclasses.replace(result, certificate=cert, info=info)
    old = problem.cost(R, t)
    if scoped.label is BoundedProblem.ROTATION_TIM:
        # Refining the rotation on the full problem would leave the subproblem's optimum.
        Rb = better[0]
        tb = min((refine_translation(problem, Rb, tt) for tt in (better[1], t)),
                 key=lambda tt: problem.cost(Rb, tt))
    else:
        Rb, tb = refine_pose(problem, *better)
    if problem.cost(Rb, tb) > problem.cost(*better):
        Rb, tb = better
    new = problem.cost(Rb, tb)
    info["better_subproblem_cost"] = cert.better_upper_bound
    if not new <= old and not accept_worse:
        info["better_subproblem_pose_full_cost"] = new
        msg = (f"{result.message}; certification found a better pose of the {scoped.label.value} "
               f"whose cost on the full problem is higher ({new:.6g} > {old:.6g}): kept the "
               f"candidate")
        return dataclasses.replace(result, certificate=cert, info=info, message=msg)
    if time_limit is not None:  # the limit covers both certifications, not each
        kw["time_limit"] = max(float(time_limit) - (time.perf_counter() - t0), 0.0)
    # A rotation subproblem's bound holds for every rotation: reused, not searched again.
    rot = scoped.label is BoundedProblem.ROTATION_TIM
    cert_new, _, _ = _certify(problem, Rb, tb, **kw, known=bound if rot else None)
    if not new <= old and not cert_new.certified:  # accept_worse: only for a certificate
        info["better_subproblem_pose_full_cost"] = new
        return dataclasses.replace(result, certificate=cert, info=info)
    worse = "" if new <= old else (f" (higher on the full problem: {new:.6g} > {old:.6g}; "
                                   "returned for its certificate)")
    if worse:
        info["candidate_T_target_source"] = result.T_target_source.tolist()
    info.update(replaced_candidate=True, candidate_cost=old, candidate_status=result.status.value,
                candidate_certificate=cert.to_dict())
    what = (f"certification found a better pose than the candidate on the {scoped.label.value} "
            f"(cost {cert.better_upper_bound:.6g} < {cert.upper_bound:.6g}; full-problem cost "
            f"{new:.6g} vs {old:.6g}){worse}; returning it, certified anew")
    return _with_pose(problem, result, Rb, tb, new, cert_new, info, what, t0,
                      before=f"Candidate ({result.status.value})")


def _with_pose(problem: WeightedTLSProblem, result: RegistrationResult, R: NDArray[np.float64],
               t: NDArray[np.float64], cost: float, cert: Certificate, info: dict[str, Any],
               what: str, t0: float, *, before: str) -> RegistrationResult:
    """``result`` with the certifier's pose ``(R, t)`` of ``cost`` in place of its own. The
    status describes the returned pose, not the one it replaced: ``CERTIFIER_POSE`` when it is
    a success, else what is wrong with it."""
    from solvers.lie import make_transform
    from solvers.registration.solve import judge_pose

    inliers = problem.inliers(R, t)
    status, message = judge_pose(problem, inliers, what)
    if status.success:
        status = SolverStatus.CERTIFIER_POSE
    return dataclasses.replace(
        result, status=status, T_target_source=make_transform(R, t), inliers=inliers, cost=cost,
        certificate=dataclasses.replace(cert, solve_time=time.perf_counter() - t0), info=info,
        message=f"{message}. {before}: {result.message}")
