"""Optimality certificates (filled by the SDP relaxations in :mod:`solvers.certify`)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Any

__all__ = ["Certificate", "CertificateStatus", "BoundedProblem", "relative_gap"]


class BoundedProblem(str, Enum):
    """Which problem a certificate's lower bound covers."""

    FULL = "full_weighted_tls"
    """The weighted TLS problem as given (joint rotation-translation relaxation)."""
    PRUNED = "pruned_weighted_tls"
    """The weighted TLS problem restricted to the max-clique survivors."""
    ROTATION_TIM = "rotation_tim_subproblem"
    """Rotation-only TLS over translation-invariant measurements (what TEASER++ certifies)."""
    ROTATION = "rotation_tls"
    """A rotation-only TLS problem given directly."""


class CertificateStatus(str, Enum):
    """Closed vocabulary of certification outcomes; only ``CERTIFIED`` certifies."""

    CERTIFIED = "certified"
    """The recomputed relative gap is within the tolerance."""
    GAP_TOO_LARGE = "gap_too_large"
    """The bound is valid but too far below the pose's cost (loose relaxation or wrong pose)."""
    INACCURATE = "inaccurate"
    """The backend stopped short of its tolerances; the bound is valid but no certificate."""
    ITERATION_LIMIT = "iteration_limit"
    """The iteration or time limit was hit."""
    INFEASIBLE = "infeasible"
    """The backend reported the relaxation infeasible (a numerical failure here)."""
    UNBOUNDED = "unbounded"
    """The backend reported the relaxation unbounded (a numerical failure here)."""
    SOLVER_ERROR = "solver_error"
    """The backend failed or returned no dual point."""
    INVALID_INPUT = "invalid_input"
    """The candidate pose or the options were malformed."""


def relative_gap(upper: float, lower: float) -> float:
    """``(upper - lower) / (1 + |upper| + |lower|)``; ``inf`` when the bound is not finite."""
    if not (abs(upper) < float("inf") and abs(lower) < float("inf")):
        return float("inf")
    return (upper - lower) / (1.0 + abs(upper) + abs(lower))


@dataclass(frozen=True)
class Certificate:
    """A duality-gap certificate for a candidate pose.

    Attributes
    ----------
    upper_bound : float
        Cost of the returned pose on the bounded problem.
    lower_bound : float
        A valid lower bound on the optimum of the bounded problem, recomputed from the dual
        point (``-inf`` when none was available).
    relative_gap : float
        ``(upper - lower) / (1 + |upper| + |lower|)``.
    certified : bool
        ``relative_gap <= tol`` from a solve that reached its tolerances.
    tol : float
        Tolerance used for ``certified``.
    problem : str
        Which problem the bound covers (a :class:`BoundedProblem` value, e.g.
        ``"full_weighted_tls"``, ``"pruned_weighted_tls"``, ``"rotation_tim_subproblem"``).
    eigenvalue_ratio : float
        Ratio of the two largest eigenvalues of the moment matrix ``Z_00`` (large means rank
        one); ``nan`` when no primal moment matrix was computed (dual-certificate path).
    backend_status : str
        Status string of the SDP backend (or of the dual-certificate iteration).
    solve_time : float
        Seconds spent certifying.
    message : str
        Why the pose is, or is not, certified.
    status : CertificateStatus
        Outcome from the closed vocabulary.
    method : str
        How the bound was obtained (``"dense"``, ``"chordal"``, ``"dual_drs"``).
    num_terms : int
        Number of TLS terms of the bounded problem.
    """

    upper_bound: float
    lower_bound: float
    relative_gap: float
    certified: bool
    tol: float
    problem: str
    eigenvalue_ratio: float
    backend_status: str
    solve_time: float
    message: str
    status: CertificateStatus = CertificateStatus.SOLVER_ERROR
    method: str = ""
    num_terms: int = 0

    @property
    def success(self) -> bool:
        """True only when the pose is certified."""
        return self.certified

    def to_dict(self) -> dict[str, Any]:
        out = {k: getattr(self, k) for k in self.__dataclass_fields__}
        out["status"] = self.status.value
        return out

    def summary(self) -> str:
        """One line for logs and the CLI."""
        verdict = "CERTIFIED" if self.certified else "not certified"
        return (
            f"{verdict} ({self.problem}, {self.method}): upper {self.upper_bound:.6g}, "
            f"lower {self.lower_bound:.6g}, relative gap {self.relative_gap:.3g} "
            f"(tol {self.tol:g}), {self.solve_time:.3g} s; {self.message}"
        )
