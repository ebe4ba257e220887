"""Optimality certificates (filled by the SDP relaxations)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["Certificate"]


@dataclass(frozen=True)
class Certificate:
    """A duality-gap certificate for a candidate pose.

    Attributes
    ----------
    upper_bound : float
        Cost of the returned pose on the bounded problem.
    lower_bound : float
        A valid lower bound on the optimum of the bounded problem.
    relative_gap : float
        ``(upper - lower) / (1 + |upper| + |lower|)``.
    certified : bool
        ``relative_gap <= tol`` from a solve whose bound was recomputed.
    tol : float
        Tolerance used for ``certified``.
    problem : str
        Which problem the bound covers (e.g. ``"full_weighted_tls"``, ``"pruned_weighted_tls"``,
        ``"rotation_tim_subproblem"``).
    eigenvalue_ratio : float
        Ratio of the two largest eigenvalues of the moment matrix (large means rank one).
    backend_status : str
        Status string of the SDP backend.
    solve_time : float
        Seconds spent certifying.
    message : str
        Why the pose is, or is not, certified.
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

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}
