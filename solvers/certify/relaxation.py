"""Black-Rangarajan (binary-cloning) liftings of weighted TLS problems.

Both liftings share one *arrowhead* structure. With ``y`` the pose vector (a unit quaternion for
the rotation problem, ``[h; vec(R); t]`` with homogenising ``h = 1`` for the full problem) and
``theta_k in {-1, +1}`` the inlier indicators, the TLS cost is the quadratic form ``x^T C x`` of
``x = [y; theta_1 y; ...; theta_K y]`` with

* ``C_00 = sum_k A_k``, ``A_k = w_k (Q_k + cbar2 E) / 2``,
* ``C_0k = C_k0 = B_k = w_k (Q_k - cbar2 E) / 4``, and zero elsewhere,

where ``y^T Q_k y`` is the normalised squared residual of term ``k`` and ``y^T E y = 1``
(``E = I`` for quaternions, ``E = e_h e_h^T`` for the full problem). Every relaxation replaces
``x x^T`` by a PSD matrix whose diagonal blocks all equal ``Z_00`` (``theta_k^2 = 1``), and whose
``Z_00`` obeys the pose constraints listed in :class:`Lifting`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.problem import WeightedTLSProblem
from solvers.procrustes import weighted_rotation
from solvers.validation import check_correspondences

__all__ = [
    "RotationTLSProblem",
    "Lifting",
    "quaternion_basis",
    "quaternion_to_rotation",
    "rotation_lifting",
    "joint_lifting",
    "tim_problem",
    "refine_rotation",
]


# ----------------------------------------------------------------------------- quaternions
def quaternion_basis() -> NDArray[np.float64]:
    """Matrices ``M[i, j]`` (3, 3, 4, 4) with ``R(q)_ij = q^T M[i, j] q`` for ``q = [x, y, z, w]``.

    Homogeneous of degree two, so ``R(q)`` is a rotation for every unit ``q``.
    """
    M = np.zeros((3, 3, 4, 4))
    x, y, z, w = range(4)

    def add(i: int, j: int, terms: list[tuple[float, int, int]]) -> None:
        for c, a, b in terms:
            M[i, j, a, b] += c / 2
            M[i, j, b, a] += c / 2

    add(0, 0, [(1, w, w), (1, x, x), (-1, y, y), (-1, z, z)])
    add(1, 1, [(1, w, w), (-1, x, x), (1, y, y), (-1, z, z)])
    add(2, 2, [(1, w, w), (-1, x, x), (-1, y, y), (1, z, z)])
    add(0, 1, [(2, x, y), (-2, w, z)])
    add(1, 0, [(2, x, y), (2, w, z)])
    add(0, 2, [(2, x, z), (2, w, y)])
    add(2, 0, [(2, x, z), (-2, w, y)])
    add(1, 2, [(2, y, z), (-2, w, x)])
    add(2, 1, [(2, y, z), (2, w, x)])
    return M


_QBASIS = quaternion_basis()


def quaternion_to_rotation(q: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix of a (not necessarily normalised) quaternion ``[x, y, z, w]``."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q)
    return np.einsum("a,ijab,b->ij", q, _QBASIS, q)


# ----------------------------------------------------------------------------- problems
@dataclass(frozen=True, eq=False)
class RotationTLSProblem:
    r"""Rotation-only weighted TLS: ``f(R) = sum_k w_k min(||b_k - R a_k||^2 / beta_k^2, cbar2)``.

    The problem TEASER++'s certifier bounds when ``a_k``, ``b_k`` are translation-invariant
    measurements (see :func:`tim_problem`).

    Parameters
    ----------
    source, target : (K, 3) array_like
        Vectors ``a_k`` and ``b_k``.
    noise_bound : float or (K,) array_like
        Positive noise bounds ``beta_k``.
    weights : (K,) array_like or None
        Non-negative weights (default 1).
    cbar2 : float
        Truncation threshold on normalised squared residuals.
    """

    source: NDArray[np.float64]
    target: NDArray[np.float64]
    noise_bound: NDArray[np.float64] = field(default=None)  # type: ignore[assignment]
    weights: NDArray[np.float64] = field(default=None)  # type: ignore[assignment]
    cbar2: float = 1.0

    def __init__(
        self,
        source: ArrayLike,
        target: ArrayLike,
        *,
        noise_bound: ArrayLike,
        weights: ArrayLike | None = None,
        cbar2: float = 1.0,
    ) -> None:
        a, b, beta, w, c2 = check_correspondences(
            source, target, noise_bound=noise_bound, weights=weights, cbar2=cbar2, min_n=1
        )
        object.__setattr__(self, "source", a)
        object.__setattr__(self, "target", b)
        object.__setattr__(self, "noise_bound", beta)
        object.__setattr__(self, "weights", w)
        object.__setattr__(self, "cbar2", c2)

    @property
    def n(self) -> int:
        return int(self.source.shape[0])

    def residuals_sq(self, rotation: ArrayLike) -> NDArray[np.float64]:
        """Normalised squared residuals ``||b_k - R a_k||^2 / beta_k^2``, shape (K,)."""
        d = self.target - self.source @ np.asarray(rotation, dtype=np.float64).T
        return np.einsum("ij,ij->i", d, d) / self.noise_bound**2

    def cost(self, rotation: ArrayLike) -> float:
        """TLS cost of the rotation ``R``."""
        return float(self.weights @ np.minimum(self.residuals_sq(rotation), self.cbar2))

    def inliers(self, rotation: ArrayLike) -> NDArray[np.bool_]:
        return self.residuals_sq(rotation) <= self.cbar2


def refine_rotation(
    problem: RotationTLSProblem, R: ArrayLike, *, max_iterations: int = 50
) -> NDArray[np.float64]:
    """Local TLS refinement: alternate inlier selection and weighted Procrustes (never worse)."""
    R = np.asarray(R, dtype=np.float64)
    best = problem.cost(R)
    w0 = problem.weights / problem.noise_bound**2
    for _ in range(max_iterations):
        S = problem.inliers(R) & (w0 > 0)
        if not S.any():
            break
        R2 = weighted_rotation((problem.target[S] * w0[S, None]).T @ problem.source[S])
        c = problem.cost(R2)
        if not c < best - 1e-14 * max(1.0, best):
            break
        R, best = R2, c
    return R


def tim_problem(
    problem: WeightedTLSProblem,
    pairs: ArrayLike | None = None,
) -> RotationTLSProblem:
    """Rotation subproblem over translation-invariant measurements (TIMs).

    TIM ``(i, j)`` is ``a_j - a_i -> b_j - b_i`` with noise bound ``beta_i + beta_j`` and weight
    ``min(w_i, w_j)``.

    Parameters
    ----------
    problem : WeightedTLSProblem
    pairs : (P, 2) int array_like or None
        The pairs; default the chain ``(k, k + 1)``.
    """
    if pairs is None:
        i = np.arange(problem.n - 1)
        pairs = np.stack([i, i + 1], axis=1)
    p = np.asarray(pairs, dtype=np.int64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"Expected `pairs` to have shape (P, 2), got {p.shape}.")
    i, j = p[:, 0], p[:, 1]
    return RotationTLSProblem(
        problem.source[j] - problem.source[i],
        problem.target[j] - problem.target[i],
        noise_bound=problem.noise_bound[i] + problem.noise_bound[j],
        weights=np.minimum(problem.weights[i], problem.weights[j]),
        cbar2=problem.cbar2,
    )


# ----------------------------------------------------------------------------- liftings
@dataclass(frozen=True, eq=False)
class Lifting:
    """Data of a lifted (arrowhead) quadratic program, see the module docstring.

    Attributes
    ----------
    kind : {"rotation", "joint"}
    A : (K, d, d) ndarray
        Per-term contributions to ``C_00``.
    B : (K, d, d) ndarray
        Off-diagonal cost blocks ``C_0k``.
    eq_mats : (L, d, d) ndarray
        Equality constraints ``<eq_mats[l], Z_00> = eq_rhs[l]``.
    eq_rhs : (L,) ndarray
    ineq_mats : (J, d, d) ndarray
        Inequality constraints ``<ineq_mats[j], Z_00> <= ineq_rhs[j]``.
    ineq_rhs : (J,) ndarray
    trace_bound : float
        ``tr(Z_00)`` is at most this on every feasible point of the relaxation.
    scale, src_center, dst_center : float, (3,), (3,)
        Normalisation of the joint lifting (points are centred and divided by ``scale``).
    """

    kind: str
    A: NDArray[np.float64]
    B: NDArray[np.float64]
    eq_mats: NDArray[np.float64]
    eq_rhs: NDArray[np.float64]
    ineq_mats: NDArray[np.float64]
    ineq_rhs: NDArray[np.float64]
    trace_bound: float
    scale: float = 1.0
    src_center: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    dst_center: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))

    @property
    def K(self) -> int:
        return int(self.A.shape[0])

    @property
    def d(self) -> int:
        return int(self.A.shape[1])

    @property
    def C00(self) -> NDArray[np.float64]:
        return self.A.sum(axis=0)

    def dense_cost(self) -> NDArray[np.float64]:
        """The full cost matrix ``C``, shape (d (K + 1), d (K + 1))."""
        K, d = self.K, self.d
        C = np.zeros((d * (K + 1), d * (K + 1)))
        C[:d, :d] = self.C00
        for k in range(K):
            s = slice(d * (k + 1), d * (k + 2))
            C[:d, s] = self.B[k]
            C[s, :d] = self.B[k]
        return C

    def pose_from_vector(self, v: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Round a lifted pose vector ``y`` (any sign, any scale) to ``(R, t)``."""
        from solvers.lie import project_to_so3

        if self.kind == "rotation":
            return quaternion_to_rotation(v), np.zeros(3)
        h = v[0]
        if abs(h) < 1e-12:
            h = 1e-12 if h >= 0 else -1e-12
        y = v / h
        R = project_to_so3(y[1:10].reshape(3, 3, order="F"))
        t_n = y[10:13] * self.scale
        return R, t_n - R @ self.src_center + self.dst_center


def rotation_lifting(problem: RotationTLSProblem) -> Lifting:
    """Quaternion lifting (QUASAR) of a rotation-only TLS problem; ``d = 4``."""
    a, b = problem.source, problem.target
    Om = np.einsum("ki,kj,ijab->kab", b, a, _QBASIS)  # b^T R a = q^T Om q
    nrm = (np.einsum("ij,ij->i", a, a) + np.einsum("ij,ij->i", b, b))[:, None, None]
    Q = (nrm * np.eye(4) - 2 * Om) / problem.noise_bound[:, None, None] ** 2
    w = problem.weights[:, None, None]
    c2 = problem.cbar2
    return Lifting(
        kind="rotation",
        A=w * (Q + c2 * np.eye(4)) / 2,
        B=w * (Q - c2 * np.eye(4)) / 4,
        eq_mats=np.eye(4)[None],
        eq_rhs=np.ones(1),
        ineq_mats=np.zeros((0, 4, 4)),
        ineq_rhs=np.zeros(0),
        trace_bound=1.0,
    )


def _sym(d: int, pairs: list[tuple[float, int, int]]) -> NDArray[np.float64]:
    """Symmetric matrix with ``y^T S y = sum c y_a y_b``."""
    S = np.zeros((d, d))
    for c, i, j in pairs:
        S[i, j] += c / 2
        S[j, i] += c / 2
    return S


def joint_lifting(problem: WeightedTLSProblem) -> Lifting:
    """Lifting of the full weighted TLS problem with ``y = [h; vec(R); t]``; ``d = 13``.

    Points are centred (weighted centroids) and scaled to unit size; the translation is
    bounded by ``T`` (see below) so that ``tr(Z_00) <= 4 + T^2``. The bound does not change the
    optimum: an optimal pose either has an inlier ``k`` with positive weight, whence
    ``||t|| <= ||b_k|| + ||a_k|| + beta_k cbar``, or every pose is optimal, ``t = 0`` included.
    """
    w = problem.weights
    sw = w.sum() if w.sum() > 0 else 1.0
    ca = w @ problem.source / sw
    cb = w @ problem.target / sw
    a0, b0 = problem.source - ca, problem.target - cb
    scale = float(max(np.abs(a0).max(), np.abs(b0).max(), 1e-12))
    a, b = a0 / scale, b0 / scale
    beta = problem.noise_bound / scale
    K, d = problem.n, 13
    cbar = np.sqrt(problem.cbar2)
    # r_k = b_k h - R a_k - t = G_k y with vec(R) column-major (R a = (a^T kron I3) vec R).
    G = np.zeros((K, 3, d))
    G[:, :, 0] = b
    for j in range(3):
        G[:, :, 1 + 3 * j: 4 + 3 * j] = -a[:, j, None, None] * np.eye(3)
    G[:, :, 10:13] = -np.eye(3)
    Q = np.einsum("kia,kib->kab", G, G) / beta[:, None, None] ** 2
    E = np.zeros((d, d))
    E[0, 0] = 1.0
    wk = w[:, None, None]
    c2 = problem.cbar2
    # Pose constraints on Z_00 (homogeneous quadratics in y).
    col = [[1 + 3 * j + i for i in range(3)] for j in range(3)]  # col[j][i] = index of R_ij
    eq: list[NDArray[np.float64]] = [E.copy()]
    rhs: list[float] = [1.0]
    for j1 in range(3):
        for j2 in range(j1, 3):
            # Columns orthonormal: c_j1 . c_j2 = delta h^2.
            S = _sym(d, [(1.0, col[j1][i], col[j2][i]) for i in range(3)])
            if j1 == j2:
                S -= E
            eq.append(S)
            rhs.append(0.0)
            # Rows orthonormal.
            S = _sym(d, [(1.0, col[m][j1], col[m][j2]) for m in range(3)])
            if j1 == j2:
                S -= E
            eq.append(S)
            rhs.append(0.0)
    # Right-handedness: c_i x c_j = c_k h for (i, j, k) cyclic.
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        for r in range(3):
            r1, r2 = (r + 1) % 3, (r + 2) % 3
            S = _sym(d, [(1.0, col[i][r1], col[j][r2]), (-1.0, col[i][r2], col[j][r1]),
                         (-1.0, col[k][r], 0)])
            eq.append(S)
            rhs.append(0.0)
    T = float(np.max(np.linalg.norm(a, axis=1) + np.linalg.norm(b, axis=1) + beta * cbar))
    Tin = np.zeros((d, d))
    Tin[10:13, 10:13] = np.eye(3)
    Tin[0, 0] = -(T**2)
    return Lifting(
        kind="joint",
        A=wk * (Q + c2 * E) / 2,
        B=wk * (Q - c2 * E) / 4,
        eq_mats=np.asarray(eq),
        eq_rhs=np.asarray(rhs),
        ineq_mats=Tin[None],
        ineq_rhs=np.zeros(1),
        trace_bound=4.0 + T**2,
        scale=scale,
        src_center=ca,
        dst_center=cb,
    )
