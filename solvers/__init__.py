"""certpose's math layer: weighted TLS registration, GNC, pruning, relaxations, certificates.

Knows nothing of scenes or features; every function takes and returns plain arrays. The top
level holds the shared vocabulary (:mod:`~solvers.problem`, :mod:`~solvers.result`,
:mod:`~solvers.certificate`, :mod:`~solvers.lie`, :mod:`~solvers.procrustes` and the public
argument checks of :mod:`~solvers.validation`); :mod:`solvers.registration` solves problems and
:mod:`solvers.certify` bounds them. ``solvers`` never imports ``certpose``.
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
