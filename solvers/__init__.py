"""certpose's math layer: weighted TLS registration, GNC, pruning, relaxations, certificates.

Knows nothing of scenes or features; every function takes and returns plain arrays.
"""

from solvers.certificate import Certificate
from solvers.problem import WeightedTLSProblem
from solvers.procrustes import weighted_procrustes
from solvers.registration import (
    GNCParams,
    PruningParams,
    solve_gnc,
    solve_pruned,
    solve_registration,
)
from solvers.result import RegistrationResult, SolverStatus

__all__ = [
    "Certificate",
    "GNCParams",
    "PruningParams",
    "RegistrationResult",
    "SolverStatus",
    "WeightedTLSProblem",
    "solve_gnc",
    "solve_pruned",
    "solve_registration",
    "weighted_procrustes",
]
