"""The public registration API."""

from __future__ import annotations

import logging
import time
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from solvers import RegistrationResult, solve_registration
from solvers.registration import from_unit_scale, unit_scale_problem
from solvers.validation import check_limit

__all__ = ["register", "as_points"]

log = logging.getLogger(__name__)

Solver = Literal["gnc", "sdp"]


def as_points(value: Any, name: str) -> Any:
    """Return ``value`` as an (N, 3) float64 array when it is an Open3D point cloud.

    Both the legacy ``open3d.geometry.PointCloud`` and the tensor
    ``open3d.t.geometry.PointCloud`` (on any device) are accepted. Other inputs pass through
    unchanged (validated by the problem type).
    """
    cls = type(value)
    if cls.__name__ != "PointCloud" or not cls.__module__.startswith("open3d"):
        return value
    if ".t." in f".{cls.__module__}.":  # tensor API: positions live in the point attributes
        if "positions" not in value.point:
            raise ValueError(f"`{name}` is an Open3D tensor point cloud without positions.")
        return np.asarray(value.point.positions.cpu().numpy(), dtype=np.float64)
    return np.asarray(value.points, dtype=np.float64)


def register(
    source: Any,
    target: Any,
    *,
    noise_bound: float | NDArray[np.float64],
    weights: NDArray[np.float64] | None = None,
    solver: Solver = "gnc",
    certify: bool = False,
    prune: Literal["auto", "always", "never"] = "auto",
    cbar2: float = 1.0,
    scope: Literal["auto", "full", "pruned", "rotation"] = "auto",
    tol: float = 1e-3,
    time_limit: float | None = None,
    prefer: Literal["certificate", "cost"] = "certificate",
    check_significance: bool = True,
) -> RegistrationResult:
    """Robustly register corresponding point sets with the weighted TLS cost.

    Parameters
    ----------
    source, target : (N, 3) array_like, open3d.geometry.PointCloud or open3d.t.geometry.PointCloud
        Corresponding points: row ``k`` of ``source`` matches row ``k`` of ``target``.
    noise_bound : float or (N,) array_like
        Inlier noise bound ``beta`` (units of the points); e.g. ``5.54 * sigma`` for isotropic
        Gaussian noise of standard deviation ``sigma``.
    weights : (N,) array_like, optional
        Non-negative correspondence weights (default 1).
    solver : {"gnc", "sdp"}
        ``"gnc"``: GNC-TLS, preceded by max-clique pruning when it pays. ``"sdp"``: the
        Black-Rangarajan SDP relaxation's own rounded pose, with its certificate.
    certify : bool
        Attach a duality-gap certificate to the returned pose (``solver="gnc"``).
    prune : {"auto", "always", "never"}
        Whether to prune with the pairwise-consistency max clique before GNC.
    cbar2 : float
        TLS truncation on normalised squared residuals (default 1).
    scope : {"auto", "full", "pruned", "rotation"}
        Which problem the certificate bounds (``certify=True`` or ``solver="sdp"``): ``"auto"``
        is the full problem for ``certify`` (clique decomposition at scale) and the TIM rotation
        subproblem for ``solver="sdp"`` (what TEASER++ certifies, ``"rotation"``).
    tol : float
        Gap tolerance of the certificate (see :class:`solvers.certificate.Certificate`).
    time_limit : float or None
        Seconds the call may spend, solving included: the certifier gets what the solver
        left (a search stops at its next check of the clock, a fraction of a second later).
        None: 120 s per bound search.
    prefer : {"certificate", "cost"}
        With ``certify=True`` and ``scope="auto"``, when the full problem cannot be certified
        (real-feature scans: too many maximal cliques) the rotation subproblem over the max
        clique's translation-invariant measurements (TEASER++'s) is certified instead.
        ``"certificate"``: return that subproblem's certified optimum (translation refined on
        the full cost) even when its full cost is higher than the solver's pose (``info``
        records the solver's pose and cost); ``"cost"``: never return a pose of higher cost
        (the certificate may then certify nothing; when the subproblem's local solvers
        already find a cheaper rotation of the subproblem whose pose costs more on the full
        problem, the subproblem's dual search, which could only refuse the pose, is skipped
        and the full problem's bound gets its time). ``certificate.problem`` names the problem
        bounded; the other problem's certificate is in ``info``. In what time is left, the full
        problem is then bounded for the returned pose by a branch and bound over poses
        (:mod:`solvers.certify.pose_bnb`): its certificate replaces the subproblem's when it
        certifies, else ``info["full_problem_certificate"]`` records the gap it proved. When it
        certifies a cheaper pose than the subproblem's (the solver's, or one it found), that
        pose is returned with the full problem's certificate, the stronger statement.
    check_significance : bool
        Report a converged pose whose consensus is no larger than random correspondences with
        the same noise bound would give as ``status="not_significant"`` (not a success; see
        :mod:`solvers.registration.significance`). Its certificate, if any, is unchanged: it
        still proves what it says about the TLS cost.

    Returns
    -------
    RegistrationResult
        With ``T_target_source`` mapping source points into the target frame. Check
        ``success``/``status``: a failed, degenerate or not significant solve is reported, not
        raised.

    Raises
    ------
    ValueError, TypeError
        On malformed input (shapes, NaN/inf, negative weights, non-positive noise bound).
    MemoryError
        ``prune="always"`` with more correspondences than memory's N^2-byte consistency graph
        holds (raised before allocating).
    """
    # Solve (and certify) at unit scale: the TLS cost, inliers and certificate bounds do not
    # depend on the units, and the solvers' tolerances are then meaningful at any scale.
    unit, scale = unit_scale_problem(
        as_points(source, "source"),
        as_points(target, "target"),
        noise_bound=noise_bound,
        weights=weights,
        cbar2=cbar2,
    )
    if solver not in ("gnc", "sdp"):
        raise ValueError(f"`solver` must be 'gnc' or 'sdp', got {solver!r}.")
    if prune not in ("auto", "always", "never"):
        raise ValueError(f"`prune` must be 'auto', 'always' or 'never', got {prune!r}.")
    # Checked even without a certificate: a misspelt scope must not pass unnoticed.
    if scope not in ("auto", "full", "pruned", "rotation"):
        raise ValueError(f"`scope` must be 'auto', 'full', 'pruned' or 'rotation', got {scope!r}.")
    if prefer not in ("certificate", "cost"):
        raise ValueError(f"`prefer` must be 'certificate' or 'cost', got {prefer!r}.")
    check_limit(time_limit, "time_limit")
    if isinstance(tol, (bool, np.bool_)) or not isinstance(tol, (int, float, np.number)):
        raise TypeError(f"`tol` must be a number, got {tol!r}.")
    if not (np.isfinite(tol) and tol > 0):  # one rule, one message: 0 and -1 alike
        raise ValueError(f"`tol` must be a positive finite number, got {tol}.")
    method = {"auto": "auto", "always": "pruned", "never": "gnc"}[prune]
    if solver == "sdp":
        from solvers.certify import solve_sdp  # cvxpy: imported on demand

        result = solve_sdp(unit, scope=scope, tol=tol, time_limit=time_limit)
    else:
        start = time.perf_counter()
        result = solve_registration(unit, method=method)  # type: ignore[arg-type]
        if certify:
            from solvers.certify import certify_result

            if time_limit is not None:  # the call's budget: what the solver left
                time_limit = max(time_limit - (time.perf_counter() - start), 1e-3)
            result = certify_result(unit, result, scope=scope, tol=tol, time_limit=time_limit,
                                    rotation_fallback=scope == "auto",
                                    prefer_certified=prefer == "certificate",
                                    pose_search=scope in ("auto", "full"))
    if check_significance:
        result = _judge_significance(unit, result)
    return from_unit_scale(result, scale)


def _judge_significance(unit: Any, result: RegistrationResult) -> RegistrationResult:
    """``result``, reported ``not_significant`` when its consensus is what chance gives."""
    from dataclasses import replace

    from solvers.registration.significance import consensus_significance
    from solvers.result import SolverStatus

    if result.status not in (SolverStatus.CONVERGED, SolverStatus.CERTIFIER_POSE):
        return result
    sig = consensus_significance(unit, result.inliers)
    info = dict(result.info, consensus_log10_nfa=sig.log10_nfa,
                consensus_pair_probability=sig.pair_probability)
    if sig.significant:
        return replace(result, info=info)
    proves = ""
    if result.certificate is not None and result.certificate.certified:
        proves = ("; the certificate proves the pose optimal for the TLS cost, not that the "
                  "correspondences are right")
    return replace(result, info=info, status=SolverStatus.NOT_SIGNIFICANT,
                   message=f"not significant: {sig.describe()}{proves}. {result.message}")
