"""certpose: certifiable robust registration and probabilistic object pose estimation.

Heavy modules (numba, cvxpy, open3d; gtsam for the bench) load on first use, so ``import certpose`` is quick.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from certpose._version import __version__

if TYPE_CHECKING:
    from certpose.api import register
    from solvers import Certificate, RegistrationResult, SolverStatus, WeightedTLSProblem

__all__ = [
    "__version__",
    "register",
    "RegistrationResult",
    "Certificate",
    "SolverStatus",
    "WeightedTLSProblem",
]

_LAZY = {
    "register": "certpose.api",
    "RegistrationResult": "solvers",
    "Certificate": "solvers",
    "SolverStatus": "solvers",
    "WeightedTLSProblem": "solvers",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'certpose' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
