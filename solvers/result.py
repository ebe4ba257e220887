"""Result and status types shared by every solver."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from enum import Enum
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from solvers.certificate import Certificate

__all__ = ["SolverStatus", "RegistrationResult"]


class SolverStatus(str, Enum):
    """Closed vocabulary of solver outcomes.

    ``CONVERGED`` and ``CERTIFIER_POSE`` count as a success.
    """

    CONVERGED = "converged"
    """The solver met its stopping rule; the pose is its estimate."""
    MAX_ITERATIONS = "max_iterations"
    """The iteration limit was hit before the stopping rule."""
    DEGENERATE = "degenerate"
    """The inliers do not fix a pose (collinear or coincident points)."""
    INSUFFICIENT_INLIERS = "insufficient_inliers"
    """Fewer than 3 consistent correspondences survived."""
    NUMERICAL_ERROR = "numerical_error"
    """A numerical failure (non-finite values, failed decomposition)."""
    SOLVER_ERROR = "solver_error"
    """A backend (e.g. an SDP solver) failed or reported an inaccurate solve."""
    CERTIFIER_POSE = "certifier_pose"
    """Certifying the solver's pose found a better one (an exact optimum of a subproblem, no
    worse on the problem posed), which is returned in its place; the solver's status and cost
    are in ``info``."""
    NOT_SIGNIFICANT = "not_significant"
    """The pose's consensus is no larger than random correspondences with the same noise
    bound would give (:mod:`solvers.registration.significance`); the pose may still be the
    certified TLS optimum, which is then no evidence of a correct registration."""

    @property
    def success(self) -> bool:
        return self in (SolverStatus.CONVERGED, SolverStatus.CERTIFIER_POSE)


@dataclass(frozen=True, eq=False)
class RegistrationResult:
    """Outcome of a robust registration.

    Attributes
    ----------
    T_target_source : (4, 4) ndarray
        Homogeneous transform mapping source points into the target frame.
    rotation : (3, 3) ndarray
        Rotation block of ``T_target_source``.
    translation : (3,) ndarray
        Translation of ``T_target_source``, in the units of the points.
    inliers : (N,) ndarray of bool
        Correspondences with normalised squared residual ``<= cbar2`` at the returned pose.
    cost : float
        Weighted TLS cost of the returned pose.
    iterations : int
        Solver iterations (GNC outer iterations, or the backend's count).
    solve_time : float
        Wall-clock time in seconds.
    success : bool
        True when ``status`` is ``CONVERGED`` or ``CERTIFIER_POSE``.
    status : SolverStatus
        Outcome from the closed vocabulary.
    message : str
        Human-readable explanation of the status.
    certificate : Certificate or None
        Optimality certificate, when certification was requested.
    solver : str
        Name of the method that produced the pose.
    info : mapping
        Solver-specific diagnostics (e.g. the max-clique size), read-only.

    Results are immutable: the arrays are read-only copies, so a caller cannot change
    ``rotation`` by writing into ``T_target_source``.
    """

    T_target_source: NDArray[np.float64]
    inliers: NDArray[np.bool_]
    cost: float
    iterations: int
    solve_time: float
    status: SolverStatus
    message: str
    certificate: Certificate | None = None
    solver: str = ""
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, dtype in (("T_target_source", np.float64), ("inliers", np.bool_)):
            arr = np.array(getattr(self, name), dtype=dtype)  # a copy the caller cannot reach
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "info", MappingProxyType(dict(self.info)))

    @classmethod
    def _fresh(cls, **values: Any) -> RegistrationResult:
        """A result from arrays the solver has just made and holds no other reference to: they
        are made read-only instead of copied (a copy costs more than a small solve's arithmetic)."""
        self = object.__new__(cls)
        d = self.__dict__
        for name, default in _RESULT_DEFAULTS:
            d[name] = values.get(name, default)
        d["info"] = MappingProxyType(dict(values.get("info") or {}))
        self.T_target_source.setflags(write=False)
        self.inliers.setflags(write=False)
        return self

    def _with_transform(self, T: NDArray[np.float64]) -> RegistrationResult:
        """This result with ``T_target_source`` replaced by the fresh array ``T``."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        T.setflags(write=False)
        object.__setattr__(new, "T_target_source", T)
        return new

    def __reduce__(self) -> tuple[Any, ...]:  # pickling (e.g. to a Dask worker)
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values["info"] = dict(self.info)
        return (_rebuild_result, (values,))

    @property
    def rotation(self) -> NDArray[np.float64]:
        return self.T_target_source[:3, :3]

    @property
    def translation(self) -> NDArray[np.float64]:
        return self.T_target_source[:3, 3]

    @property
    def success(self) -> bool:
        return self.status.success

    @property
    def num_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary of the result."""
        out: dict[str, Any] = {
            "T_target_source": self.T_target_source.tolist(),
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "num_inliers": self.num_inliers,
            "inliers": np.flatnonzero(self.inliers).tolist(),
            "cost": self.cost,
            "iterations": self.iterations,
            "solve_time": self.solve_time,
            "success": self.success,
            "status": self.status.value,
            "message": self.message,
            "solver": self.solver,
            "certificate": None if self.certificate is None else self.certificate.to_dict(),
            "info": {k: _jsonable(v) for k, v in self.info.items()},
        }
        return out


_RESULT_DEFAULTS = tuple((f.name, f.default) for f in fields(RegistrationResult))


def _rebuild_result(values: dict[str, Any]) -> RegistrationResult:
    return RegistrationResult(**values)


def _jsonable(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        return v.item()
    if isinstance(v, Enum):
        return v.value
    return v
