"""Optimality certificates (filled by the SDP relaxations in :mod:`solvers.certify`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from typing import Any

__all__ = [
    "Certificate",
    "CertificateStatus",
    "BoundedProblem",
    "relative_gap",
    "undiluted_gap",
]


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
    """The literature's gap ``(upper - lower) / (1 + |upper| + |lower|)``; ``inf`` if not finite.

    With many outliers it is diluted by their constant cost: see :func:`undiluted_gap`.
    """
    if not (abs(upper) < float("inf") and abs(lower) < float("inf")):
        return float("inf")
    return (upper - lower) / (1.0 + abs(upper) + abs(lower))


def undiluted_gap(upper: float, lower: float, outlier_cost: float) -> float:
    """``(upper - lower) / (1 + |upper - c| + |lower - c|)`` with ``c`` the outlier cost.

    ``c`` is the cost the candidate pays for its outliers (``cbar2`` times their weights), a
    constant that fills ``|upper|`` at high outlier rates: at ``N = 1000`` with 99% outliers the
    literature's gap accepts an absolute slack of about 2 (two correspondences' worth), this one
    about ``tol`` times the inlier cost. It is never smaller than :func:`relative_gap` when
    ``0 <= c <= upper``.
    """
    if not (abs(upper) < float("inf") and abs(lower) < float("inf")):
        return float("inf")
    return (upper - lower) / (1.0 + abs(upper - outlier_cost) + abs(lower - outlier_cost))


def _json_safe(value: Any) -> Any:
    """NaN/inf -> None, tuples -> lists, enums -> values (valid JSON, ``allow_nan=False``)."""
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (tuple, list)):
        return [_json_safe(v) for v in value]
    return value


@dataclass(frozen=True)
class Certificate:
    """A duality-gap certificate for a candidate pose.

    Attributes
    ----------
    upper_bound : float
        Cost of the certified pose on the bounded problem, in the user's units (exactly the
        pose the certificate is attached to).
    lower_bound : float
        A valid lower bound on the optimum of the bounded problem, in the user's units,
        recomputed from the dual point(s) with an allowance for floating-point error in the
        eigenvalues (``-inf`` when none was available).
    relative_gap : float
        The gap ``certified`` is decided on: :func:`undiluted_gap` on the *normalised* problem
        (weights divided by ``weight_scale``, so one average correspondence's outlier cost is
        ``cbar2``; the liftings also centre and scale the points), i.e.
        ``(u - l) / (1 + |u - c| + |l - c|)`` with ``u, l`` the normalised bounds and ``c`` the
        candidate's normalised outlier cost. It depends neither on the units of the points nor
        on those of the weights, and is not diluted by the outliers' constant cost.
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
    literature_gap : float
        ``(u - l) / (1 + |u| + |l|)`` on the normalised problem, for comparison with other
        solvers (diluted by the outliers' cost at high outlier rates).
    weight_scale : float
        The normalisation: costs in the user's units are ``weight_scale`` times the normalised
        ones (the mean positive weight of the bounded problem).
    outlier_cost : float
        The candidate's outlier cost ``c`` on the bounded problem, in the user's units.
    indices : tuple of int or None
        Terms of the user's problem the bounded problem is built from (max-clique survivors
        for the pruned and rotation scopes); ``None``: all of them.
    pairs : tuple of (int, int) or None
        For the rotation scope, the TIM pairs ``(i, j)`` (indices of the user's problem): TIM
        ``a_j - a_i -> b_j - b_i``.
    cliques : tuple of tuple of int or None
        For the full problem bounded by clique decomposition, the maximal cliques of the
        pairwise-consistency graph whose bounds were computed (all those that could beat
        ``upper_bound``); the lower bound is the least, over them, of the clique subproblem's
        bound plus the outlier cost of everything outside it.
    better_upper_bound : float or None
        Cost on the bounded problem of a better pose found while certifying (the candidate is
        then not the bounded problem's optimum); ``None`` when none was found.
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
    literature_gap: float = float("nan")
    weight_scale: float = 1.0
    outlier_cost: float = float("nan")
    indices: tuple[int, ...] | None = None
    pairs: tuple[tuple[int, int], ...] | None = None
    cliques: tuple[tuple[int, ...], ...] | None = None
    better_upper_bound: float | None = None

    @property
    def success(self) -> bool:
        """True only when the pose is certified."""
        return self.certified

    def to_dict(self) -> dict[str, Any]:
        """Plain data for JSON (NaN and inf become ``None``)."""
        return {k: _json_safe(getattr(self, k)) for k in self.__dataclass_fields__}

    def summary(self) -> str:
        """One line for logs and the CLI."""
        verdict = "CERTIFIED" if self.certified else "not certified"
        return (
            f"{verdict} ({self.problem}, {self.method}): upper {self.upper_bound:.6g}, "
            f"lower {self.lower_bound:.6g}, gap {self.relative_gap:.3g} (tol {self.tol:g}; "
            f"literature gap {self.literature_gap:.3g}), {self.solve_time:.3g} s; {self.message}"
        )
