"""A closed-form lower bound on a clique subproblem whose least-squares pose keeps every term.

Why it is sound
---------------
Let ``p_C`` be the weighted least-squares pose of all terms ``C`` (weights ``v = w / beta^2``),
in coordinates centred on the ``v``-weighted means (so its translation is 0), ``rho_i`` the
residual vectors there. For an inlier set ``S = C \\ O`` the least-squares optimum is

    ``LS_S = A_S + B_S - 2 lambda_max(N(H_S))``

(Horn: ``A_S, B_S`` the centred sums of squares, ``N(H)`` the 4x4 quaternion matrix of the
cross-covariance ``H_S``, ``q^T N(H) q = sum v (R(q) a) . b``). With ``q`` the top eigenvector
of ``N(H_C)``, ``E = N(H_S) - N(H_C)`` and ``gamma`` the eigengap, the secular equation gives
``lambda_max(N(H_S)) <= lambda_1 + q^T E q + |(I - q q^T) E q|^2 / (gamma - 2 |E|)`` whenever
``gamma > 2 |E|``. The first two terms are the least squares of ``S`` at ``R(q)``, so

    ``LS_S >= LS_C(R(q)) - first(O) - 2 sec(O)``,
    ``first(O) = sum_O v |rho_i|^2 + |sum_O v rho_i|^2 / V_S``,

and ``sec(O)`` is bounded with ``|(I - q q^T) N(a b^T) q| <= |a| |b - R a|`` (``q`` is an
eigenvector of the aligned pair's matrix) and ``|N(a b^T)| = |a| |b|``:

    ``sec(O) <= (sum_O v |a_i| |rho_i| + |x| |sum_O v rho_i| / V_S)^2
               / (gamma - 2 (sum_O v |a_i| |b_i| + |x| |y| / V_S))``,
    ``x = sum_O v a_i``, ``y = sum_O v b_i``.

A pose whose outliers include ``O`` costs at least ``cbar2 W(O) + LS_S``; sets with
``cbar2 W(O) >= LS_C`` cannot beat ``LS_C``. Every term of these bounds grows with ``O``, so
over the sets of ``k`` terms each sum is bounded by its ``k`` largest terms (sorted
separately). When the least-squares residuals are well inside the noise bound, removing terms
never pays and the bound is ``LS_C`` itself: the exact optimum, in closed form, where the
branch and bound over inlier sets needed millions of nodes (all-inlier cliques of 100 terms).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solvers.problem import WeightedTLSProblem

__all__ = ["AllInlierBound", "all_inlier_bound", "horn_matrix"]

_EPS = float(np.finfo(np.float64).eps)


@dataclass(frozen=True)
class AllInlierBound:
    """Result of :func:`all_inlier_bound` (costs in the problem's units).

    Attributes
    ----------
    lower : float
        Sound lower bound on the problem's TLS minimum (less a rounding allowance).
    cost : float
        TLS cost of ``rotation, translation`` (the least-squares pose of every term).
    rotation, translation : ndarray
        That pose, (3, 3) and (3,).
    exact : bool
        No set of outliers can lower the cost: ``lower`` is the least-squares optimum.
    """

    lower: float
    cost: float
    rotation: NDArray[np.float64]
    translation: NDArray[np.float64]
    exact: bool


def horn_matrix(H: NDArray[np.float64]) -> NDArray[np.float64]:
    """Horn's 4x4 matrix ``N`` of a cross-covariance ``H = sum v a b^T``: ``q^T N q`` is
    ``sum v (R(q) a) . b`` for a unit quaternion ``q = (w, x, y, z)``."""
    Sxx, Sxy, Sxz = H[0]
    Syx, Syy, Syz = H[1]
    Szx, Szy, Szz = H[2]
    return np.array([
        [Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx],
        [Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz],
        [Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy],
        [Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz],
    ])


def quaternion_rotation(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrix of the unit quaternion ``q = (w, x, y, z)``."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
    ])


def _top_sums(values: NDArray[np.float64], kmax: int) -> NDArray[np.float64]:
    """(kmax,) sums of the k largest values, k = 1..kmax."""
    return np.cumsum(np.sort(values)[::-1][:kmax])


def all_inlier_bound(problem: WeightedTLSProblem) -> AllInlierBound | None:
    """Lower bound on ``problem``'s TLS minimum from its all-terms least-squares pose (module
    docstring); ``None`` when that pose leaves a term outside the noise bound or the eigengap
    is too small for the bound (then it says nothing)."""
    w = problem.weights
    v = w / problem.noise_bound**2
    V = float(v.sum())
    if not V > 0:
        return None
    ca = (v @ problem.source) / V
    cb = (v @ problem.target) / V
    a, b = problem.source - ca, problem.target - cb
    N = horn_matrix((v[:, None] * a).T @ b)
    lam, Q = np.linalg.eigh(N)
    q = Q[:, -1]
    R = quaternion_rotation(q)
    # q is an eigenvector up to rounding: the residual r shifts every eigenvalue by <= 2 |r|.
    lam1 = float(q @ N @ q)
    r_norm = float(np.linalg.norm(N @ q - lam1 * q))
    gamma = lam1 - float(lam[-2]) - 4 * r_norm
    rho = a @ R.T - b
    r2 = np.einsum("ij,ij->i", rho, rho)
    cost_ls = float(v @ r2)
    t = cb - R @ ca
    c2 = problem.cbar2
    if not np.all(r2 / problem.noise_bound**2 < c2):
        return None
    # Sets O that could beat LS_C: cbar2 W(O) < LS_C, at most kmax terms.
    kmax = int(np.searchsorted(np.cumsum(np.sort(w)), cost_ls / c2, side="left"))
    kmax = min(max(kmax, 0), problem.n - 1)
    rho_n = np.sqrt(r2)
    a_n = np.linalg.norm(a, axis=1)
    b_n = np.linalg.norm(b, axis=1)
    scale = float(v @ (a_n**2 + b_n**2)) + c2 * float(w.sum())
    allowance = 64 * _EPS * (scale + 1.0) + 8 * r_norm
    worst = 0.0
    if kmax > 0:
        own = _top_sums(v * r2 - c2 * w, kmax)  # first(O)'s separable part less cbar2 W(O)
        vr = _top_sums(v * rho_n, kmax)  # bounds |sum_O v rho_i|
        va = _top_sums(v * a_n, kmax)  # bounds |x|
        vb = _top_sums(v * b_n, kmax)  # bounds |y|
        var = _top_sums(v * a_n * rho_n, kmax)
        vab = _top_sums(v * a_n * b_n, kmax)
        VS = V - _top_sums(v, kmax)
        if np.any(VS <= 0):
            return None
        E = vab + va * vb / VS
        room = gamma - 2 * E
        if np.any(room <= 0):
            return None
        sec = (var + va * vr / VS) ** 2 / room
        U = own + vr**2 / VS + 2 * sec
        worst = float(max(U.max(), 0.0))
    lower = cost_ls - worst - allowance
    return AllInlierBound(lower=float(max(lower, 0.0)), cost=problem.cost(R, t), rotation=R,
                          translation=t, exact=worst == 0.0)
