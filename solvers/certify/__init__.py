"""Certificates of global optimality for weighted TLS registration.

Owns the Black-Rangarajan relaxations (rotation over translation-invariant measurements, and the
joint rotation-translation lifting), their interior-point (cvxpy + Clarabel) and first-order
dual searches, the clique decomposition of the full problem with closed forms (cliques of one
or two terms, cliques whose least-squares pose keeps every term) and exact branch and bound
per clique, a branch and bound over poses when the cliques are too many to list, the
shared-source bound of correspondences grouped by source point (eq. (2)'s
candidates), and the front end that turns a bound into a :class:`solvers.Certificate`. May
import the public modules of :mod:`solvers` and :mod:`solvers.registration`; nothing imports it
but callers who ask for a certificate (it loads cvxpy on demand).
"""

from solvers.certify.front import (
    certify_pose,
    certify_result,
    certify_rotation,
    rebuild_bounded_problem,
    refine_pose,
    refine_rotation,
    refine_translation,
    rotation_gnc,
    solve_sdp,
)

CERTIFY_KERNELS = ("solvers.certify._kernels:heavy_maximal_cliques",
                   "solvers.registration._kernels:consistency_edge_list",
                   "solvers.certify._pose_kernels:pose_bnb",
                   "solvers.certify._kernels:pair_minimum")
"""The compiled kernels a full-problem certificate calls on every graph that is not a clique (for
:func:`solvers.jit.warm_up`; the branch and bound over poses on graphs with too many maximal
cliques to list, the pairs of the shared-source bound); the per-clique branch and bound and the
rotation dual's projection compile on first use."""

__all__ = [
    "CERTIFY_KERNELS",
    "certify_pose",
    "certify_result",
    "certify_rotation",
    "refine_pose",
    "refine_rotation",
    "refine_translation",
    "rotation_gnc",
    "solve_sdp",
    "rebuild_bounded_problem",
]
