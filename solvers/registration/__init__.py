"""Robust registration: GNC-TLS, max-clique pruning and scalar TLS voting.

Owns the solvers that turn a :class:`solvers.WeightedTLSProblem` into a
:class:`solvers.RegistrationResult`, their numba kernels, and the test of whether a consensus
beats random correspondences (:mod:`~solvers.registration.significance`). May import the public modules of
:mod:`solvers` (problem, result, lie, procrustes, validation); never :mod:`solvers.certify`.
"""

from solvers.registration.pruning import (
    consistency_graph,
    max_clique,
    maximum_cliques,
    prune_max_clique,
    prune_maximum_cliques,
    scalar_tls,
    vote_translation,
)
from solvers.registration.solve import (
    LARGE_CORE_KERNELS,
    PRUNED_SOLVE_KERNELS,
    GNCParams,
    PruningParams,
    check_graph_memory,
    degeneracy,
    from_unit_scale,
    solve_gnc,
    solve_pruned,
    solve_registration,
    to_unit_scale,
    unit_scale_problem,
)

__all__ = [
    "LARGE_CORE_KERNELS",
    "PRUNED_SOLVE_KERNELS",
    "GNCParams",
    "PruningParams",
    "check_graph_memory",
    "consistency_graph",
    "degeneracy",
    "from_unit_scale",
    "max_clique",
    "maximum_cliques",
    "prune_max_clique",
    "prune_maximum_cliques",
    "scalar_tls",
    "solve_gnc",
    "solve_pruned",
    "solve_registration",
    "to_unit_scale",
    "unit_scale_problem",
    "vote_translation",
]
