"""Dual certificates of a candidate solution, found by Douglas-Rachford splitting.

For the dense (QUASAR) relaxation of an arrowhead :class:`~solvers.certify.relaxation.Lifting` and a
rank-one candidate ``x = [y; theta_1 y; ...; theta_K y]``, a dual certificate is a dual matrix
``S = C - blkdiag(D_0..D_K) - W`` (``W`` with skew off-diagonal blocks, ``sum_k D_k`` in the span
of the pose constraints) with ``S x = 0`` and ``S >= 0``. The affine conditions form a set ``A``;
Douglas-Rachford alternates the projection onto ``A`` and onto the PSD cone (one
eigendecomposition); :func:`_drs_iterates` is the iteration, shared with
:mod:`solvers.certify.joint_dual` (the joint rotation-translation lifting). This follows the idea
of TEASER++'s certifier (Yang, Shi, Carlone 2020).

:func:`rotation_dual_certificate` specialises the search to the quaternion lifting, as TEASER++'s
certifier does. The target vectors are first rotated by ``R^T`` so that the candidate is the
identity (the relaxation is invariant under this change of variables); the lifted candidate is
then ``theta kron e_4``. In that frame the affine projection has a closed form (its normal
matrix is ``(K + 3)/4 I - J/4``, inverted by Sherman-Morrison), so an iteration costs the
lowest few eigenpairs and a Cholesky test; and the search starts from a closed-form dual point:
the multipliers of ``Z_kk = Z_00`` chosen per term from stationarity and the term's geometry
(Yang, Shi, Carlone 2020, appendix), which is often PSD already.

Whatever point the iteration stops at, the bound is recomputed by
:func:`solvers.certify.sdp_relaxation.bound_from_dense_dual`, so it is valid even when the iteration
has not converged.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solvers.certify._threads import single_thread_blas
from solvers.certify.relaxation import (
    Lifting,
    RotationTLSProblem,
    quaternion_to_rotation,
    refine_rotation,
    rotation_lifting,
)
from solvers.certify.sdp_relaxation import bound_from_dense_dual
from solvers.jit import compiled
from solvers.lie import project_to_so3

__all__ = ["DualCertificateResult", "rotation_dual_certificate"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DualCertificateResult:
    """Outcome of a dual certificate search (:func:`rotation_dual_certificate`,
    :func:`solvers.certify.joint_dual.joint_dual_certificate`).

    Attributes
    ----------
    lower_bound : float
        Sound lower bound on the dense relaxation's optimum (hence on the problem's).
    upper_bound : float
        ``x^T C x``, the lifted cost of the candidate.
    min_eig : float
        Smallest eigenvalue of the repaired dual matrix.
    iterations : int
    converged : bool
        The relative gap reached the target.
    solve_time : float
    rotation : (3, 3) ndarray or None
        :func:`rotation_dual_certificate` only: the candidate the search ended with (better
        than the given one when a rounding improved it).
    """

    lower_bound: float
    upper_bound: float
    min_eig: float
    iterations: int
    converged: bool
    solve_time: float
    rotation: NDArray[np.float64] | None = None


def _psd_part(M: NDArray[np.float64]) -> NDArray[np.float64]:
    """Projection onto the PSD cone.

    A full divide-and-conquer ``eigh`` measured 2x faster than LAPACK's ``evr`` restricted to
    the negative eigenvalues (n = 84 to 404, one thread).
    """
    w, V = np.linalg.eigh(M)
    neg = w < 0
    if not neg.any():
        return M
    Vn = V[:, neg]
    return M - (Vn * w[neg]) @ Vn.T


def _drs_iterates(
    step: Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.float64]]],
    M: NDArray[np.float64],
    max_iterations: int,
    anderson: int,
) -> Iterator[tuple[int, NDArray[np.float64]]]:
    """Affine points of the relaxed Douglas-Rachford iteration, ``(iteration, S)`` from 0.

    ``step(M)`` returns the fixed-point residual ``T(M) - M`` and the affine point. With
    ``anderson > 0`` the iteration is sped up by safeguarded type-II Anderson acceleration of
    memory ``anderson``; it only moves the iterate, every bound is recomputed by the caller
    from the affine point.
    """
    g, S = step(M)
    yield 0, S
    dX: list[NDArray[np.float64]] = []
    dG: list[NDArray[np.float64]] = []
    for it in range(1, max_iterations + 1):
        M_plain = M + g
        M_new = M_plain
        if anderson and dX:
            G = np.stack([v.ravel() for v in dG], axis=1)
            X = np.stack([v.ravel() for v in dX], axis=1)
            gam = np.linalg.lstsq(G, g.ravel(), rcond=1e-10)[0]
            M_new = M_plain - ((X + G) @ gam).reshape(M.shape)
        g_new, S_new = step(M_new)
        if anderson and dX and np.linalg.norm(g_new) > 2.0 * np.linalg.norm(g):
            # Safeguard: reject the extrapolation, restart the memory from the plain step.
            dX.clear()
            dG.clear()
            M_new = M_plain
            g_new, S_new = step(M_new)
        if anderson:
            dX.append(M_new - M)
            dG.append(g_new - g)
            if len(dX) > anderson:
                dX.pop(0)
                dG.pop(0)
        M, g, S = M_new, g_new, S_new
        yield it, S


def _hat(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cross-product matrices of the rows of ``v`` (K, 3) -> (K, 3, 3)."""
    H = np.zeros(v.shape[:-1] + (3, 3))
    H[..., 0, 1], H[..., 0, 2], H[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    H[..., 1, 0], H[..., 2, 0], H[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return H


def _rotation_initial_dual(
    lift: Lifting, a: NDArray[np.float64], xi: NDArray[np.float64], theta: NDArray[np.float64],
    w: NDArray[np.float64], cbar2: float, f: float,
) -> NDArray[np.float64]:
    """Closed-form dual point in the identity frame, blocks (K + 1, K + 1, 4, 4).

    ``a`` and ``xi = R^T b - a`` are divided by the noise bounds. The last row and column of
    each multiplier block are forced by ``S x = 0``; the 3 x 3 part is the per-term choice of
    the TEASER++ appendix. Every block keeps the exact dual structure, so the point is feasible
    for the bound whatever the data.
    """
    K = a.shape[0]
    nb = K + 1
    inl = theta > 0
    ci = np.where(inl, 0.75, 0.25)  # share of |xi|^2 kept by the block
    cv = np.where(inl, 1.5, 0.5)
    xx = np.einsum("ki,ki->k", xi, xi)
    ha = _hat(a)
    blk = np.zeros((K, 4, 4))
    blk[:, :3, :3] = (
        ha @ ha
        - np.einsum("ki,ki->k", a, xi)[:, None, None] * np.eye(3)
        + 0.5 * (np.einsum("ki,kj->kij", a, xi) + np.einsum("ki,kj->kij", xi, a))
        - (ci * xx + 0.25 * cbar2)[:, None, None] * np.eye(3)
    )
    blk[:, :3, 3] = -cv[:, None] * np.cross(xi, a)
    blk[:, 3, :3] = blk[:, :3, 3]
    blk[:, 3, 3] = -ci * xx - (1 - ci) * cbar2
    blk *= w[:, None, None]
    S = np.zeros((nb, nb, 4, 4))
    S[0, 0] = -f * np.eye(4) - blk.sum(axis=0)
    S[0, 1:] = lift.B
    S[1:, 0] = lift.B
    k = np.arange(1, nb)
    S[k, k] = lift.A + blk
    return S


class _IdentityFrameProjector:
    """Closed-form projection onto the dual affine set of the quaternion lifting, identity frame.

    The set: ``S = S_init + D`` where ``D`` has skew off-diagonal blocks, diagonal blocks that
    sum to zero with a zero ``(4, 4)`` entry, and ``D x = 0`` for ``x = theta kron e_4``. Only the
    last columns of the blocks are coupled (by ``D x = 0``); the normal matrix of that coupling is
    ``(K + 3)/4 I - J/4`` whatever ``theta``, with inverse ``4/(K + 3) (I + J/2)``.
    """

    def __init__(self, S_init: NDArray[np.float64], th: NDArray[np.float64]) -> None:
        self.nb = th.size
        self.S_init = S_init
        self.th = np.ascontiguousarray(th, dtype=np.float64)
        self.Theta = np.outer(th, th)
        self.c = 4.0 / (self.nb + 2)  # 4 / (K + 3)

    def __call__(self, M: NDArray[np.float64]) -> NDArray[np.float64]:
        identity_frame_projection = compiled("solvers.certify._kernels").identity_frame_projection

        # Compiled: the numpy version below costs 0.2-0.4 ms of Python overhead per call at
        # K = 20, as much as the eigendecomposition.
        return identity_frame_projection(M, self.S_init, self.th, self.c)

    def reference(self, M: NDArray[np.float64]) -> NDArray[np.float64]:
        """The same projection in numpy (the specification the kernel is tested against)."""
        nb = self.nb
        n = 4 * nb
        G = (M - self.S_init).reshape(nb, 4, nb, 4).transpose(0, 2, 1, 3)
        out = np.empty_like(G)
        X = G[:, :, :3, :3]
        out[:, :, :3, :3] = 0.5 * (X - np.swapaxes(X, 2, 3))
        idx = np.arange(nb)
        V = 0.5 * (G[:, :, :3, 3] - G[:, :, 3, :3])
        V[idx, idx] = 0.0
        dg = G[idx, idx]
        u = 0.5 * (dg[:, :3, 3] + dg[:, 3, :3])
        rho = u + np.einsum("ij,ijc->ic", self.Theta, V)
        lam = self.c * (rho + 0.5 * rho.sum(axis=0))
        V -= 0.25 * self.Theta[:, :, None] * (lam[:, None, :] - lam[None, :, :])
        V[idx, idx] = 0.0
        u -= 0.5 * lam
        out[:, :, :3, 3] = V
        out[:, :, 3, :3] = -V
        out[:, :, 3, 3] = 0.0
        E = 0.5 * (dg[:, :3, :3] + np.swapaxes(dg[:, :3, :3], 1, 2))
        out[idx, idx] = 0.0
        out[idx, idx, :3, :3] = E - E.mean(axis=0)
        out[idx, idx, :3, 3] = u
        out[idx, idx, 3, :3] = u
        return self.S_init + out.transpose(0, 2, 1, 3).reshape(n, n)


class _NegativePart:
    """Projection onto the PSD cone for a sequence of iterates, computing only the negative
    eigenpairs while they are few.

    LAPACK ``evr`` restricted to the negative eigenvalues costs about in proportion to their
    number; the full divide-and-conquer ``eigh`` wins once they are more than about n / 8
    (measured on one thread: n = 404 with 20 negative, 6.7 against 13.8 ms; with 120, 20.7
    against 14.1 ms). Iterates of one search change slowly, so the previous iterate's count
    chooses the method. Near a certificate an iterate has 1-5 negative eigenvalues; on real FPFH
    correspondences (K = 107, n = 432) 15-37 throughout a search of hundreds of iterations.
    """

    def __init__(self) -> None:
        self.count: int | None = None

    def __call__(self, M: NDArray[np.float64]) -> NDArray[np.float64]:
        from scipy.linalg import eigh

        n = M.shape[0]
        if n < 64 or (self.count is not None and self.count > n // 8):
            w, V = np.linalg.eigh(M)
        else:
            w, V = eigh(M, subset_by_value=(-np.inf, 0.0), driver="evr", check_finite=False)
        neg = w < 0
        self.count = int(neg.sum())
        if not self.count:
            return M
        Vn = V[:, neg]
        return M - (Vn * w[neg]) @ Vn.T


def _is_pd(S: NDArray[np.float64], delta: float) -> bool:
    """Whether ``S + delta I`` is positive definite (a Cholesky factorisation succeeds)."""
    try:
        np.linalg.cholesky(S + delta * np.eye(S.shape[0]))
    except np.linalg.LinAlgError:
        return False
    return True


def _identity_frame_start(
    problem: RotationTLSProblem, R: NDArray[np.float64]
) -> tuple[Lifting, float, NDArray[np.float64], NDArray[np.float64]]:
    """Lifting, cost, ``[1; theta]`` and closed-form dual point of ``R`` in its identity frame."""
    b_id = problem.target @ R  # rows R^T b_k: the candidate becomes the identity
    ident = RotationTLSProblem(problem.source, b_id, noise_bound=problem.noise_bound,
                               weights=problem.weights, cbar2=problem.cbar2)
    lift = rotation_lifting(ident)
    f = ident.cost(np.eye(3))
    theta = np.where(ident.inliers(np.eye(3)), 1.0, -1.0)
    beta = problem.noise_bound[:, None]
    a = problem.source / beta
    S_blocks = _rotation_initial_dual(lift, a, b_id / beta - a, theta, problem.weights,
                                      problem.cbar2, f)
    nb = theta.size + 1
    return lift, f, np.concatenate([[1.0], theta]), S_blocks.transpose(0, 2, 1, 3).reshape(
        4 * nb, 4 * nb)


def _round_negative_directions(
    problem: RotationTLSProblem, R: NDArray[np.float64], S: NDArray[np.float64], count: int
) -> NDArray[np.float64]:
    """Best rotation rounded from the most negative eigenvectors of the dual matrix ``S``.

    A direction ``v`` with ``v^T S v < 0`` points at lifted points the candidate's dual cannot
    exclude: its block average ``sum_k v_k v_k^T`` is rounded to a quaternion (identity frame),
    mapped back and refined locally. Returns ``R`` itself (the same object) when nothing is
    better.
    """
    w, V = np.linalg.eigh(S)
    best, best_cost = R, problem.cost(R)
    # The candidate itself refined, in case it was not stationary.
    cands = [refine_rotation(problem, R)]
    for i in range(min(count, int((w < 0).sum()))):
        v = V[:, i].reshape(-1, 4)
        q = np.linalg.eigh(v.T @ v)[1][:, -1]
        cands.append(refine_rotation(problem, R @ quaternion_to_rotation(q)))
    for Rc in cands:
        c = problem.cost(Rc)
        if c < best_cost - 1e-12 * max(1.0, best_cost):
            best, best_cost = Rc, c
    return best


def rotation_dual_certificate(
    problem: RotationTLSProblem,
    R: NDArray[np.float64],
    *,
    tol: float = 1e-3,
    max_iterations: int = 500,
    time_limit: float | None = None,
    relaxation: float = 1.99,
    restart_every: int = 40,
    outlier_cost: float = 0.0,
) -> DualCertificateResult:
    """Search a dual certificate of the rotation ``R`` for the QUASAR relaxation of ``problem``.

    A certificate exists only at the relaxation's optimum. When the search has not converged
    after ``restart_every`` iterations, rotations are rounded from the most negative
    eigenvectors of the dual matrix and refined locally; if one is better than the current
    candidate, the search restarts from it (measured on YCB-Video eq. (2) problems, K = 10-12:
    GNC and local refinement missed the optimum, one rounding found it).

    Parameters
    ----------
    problem : RotationTLSProblem
    R : (3, 3) ndarray
        Candidate rotation, preferably locally refined (stationary).
    tol : float
        Target relative gap ``(f - lb) / (1 + |f| + |lb|)``, ``f`` the cost of the final
        candidate.
    max_iterations : int
        Douglas-Rachford iterations, restarts included.
    time_limit : float or None
        Seconds after which the iteration stops.
    relaxation : float
        Over-relaxation of the Douglas-Rachford step, in (0, 2).
    restart_every : int
        Iterations without convergence before a rounding is tried (0: never).
    outlier_cost : float
        Constant ``c`` of the target gap ``(f - lb) / (1 + |f - c| + |lb - c|)``
        (:func:`solvers.certificate.undiluted_gap`, what the certificate's verdict uses: pass the
        candidate's outlier cost); 0 gives the literature's gap above.

    Returns
    -------
    DualCertificateResult
        ``lower_bound`` is recomputed by :func:`solvers.certify.sdp_relaxation.bound_from_dense_dual`
        from the dual points, so it is valid whether or not the iteration converged (every
        frame bounds the same problem; the best bound is kept). ``rotation`` is the final
        candidate and ``upper_bound`` its cost.
    """
    t0 = time.perf_counter()
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"Expected `R` to be a finite (3, 3) rotation, got shape {R.shape}.")
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
        raise ValueError("Expected `R` to be a rotation matrix (orthonormal, det +1).")
    # The change of frame bounds the same problem only if it is an exact isometry.
    R = project_to_so3(R)
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"`tol` must be a positive finite scalar, got {tol!r}.")
    if not 0 < relaxation < 2:
        raise ValueError(f"`relaxation` must lie in (0, 2), got {relaxation!r}.")
    if max_iterations < 0 or restart_every < 0:
        raise ValueError("`max_iterations` and `restart_every` must be non-negative, got "
                         f"{max_iterations!r} and {restart_every!r}.")
    best_lb, best_eig, it = -np.inf, np.nan, 0

    c = float(outlier_cost)

    def rel(lb: float, f: float) -> float:
        return (f - lb) / (1 + abs(f - c) + abs(lb - c))

    # One BLAS thread: many mid-sized eigendecompositions oversubscribe a loaded machine
    # (measured 10-100x slower multi-threaded on 2 busy cores).
    with single_thread_blas():
        while True:  # one pass per candidate
            lift, f, th, S_init = _identity_frame_start(problem, R)
            project = _IdentityFrameProjector(S_init, th)
            nb = th.size
            # On the affine set f + (K + 1) min(lambda_min, 0) is a bound (y = f, trace bound
            # 1), so the target gap is reached once S + delta I is positive definite: a
            # Cholesky test, 10x cheaper than the smallest eigenvalue. The returned bound is
            # recomputed from scratch.
            delta = 0.5 * tol * (1 + 2 * abs(f - c)) / (nb * (1 + tol))
            M, local, R_new, S = S_init, 0, None, S_init
            psd_part = _NegativePart()
            done = _is_pd(S_init, delta)
            while not done and it < max_iterations:
                it += 1
                local += 1
                P = psd_part(M)
                S = project(2 * P - M)
                if _is_pd(S, delta):
                    break
                if time_limit is not None and time.perf_counter() - t0 > time_limit:
                    break
                if restart_every and local % restart_every == 0:
                    Rc = _round_negative_directions(problem, R, S, 4)
                    if Rc is not R:
                        R_new = Rc
                        break
                M = M + relaxation * (S - P)
            best_S = S
            lb, lam = bound_from_dense_dual(lift, best_S)
            if lb > best_lb:
                best_lb, best_eig = lb, lam
            if R_new is None:
                break
            log.debug("dual search: restart from a rounded rotation, cost %.6g -> %.6g", f,
                      problem.cost(R_new))
            R = R_new
    f = problem.cost(R)
    return DualCertificateResult(
        lower_bound=float(best_lb),
        upper_bound=float(f),
        min_eig=float(best_eig),
        iterations=it,
        converged=bool(rel(best_lb, f) <= tol),
        solve_time=time.perf_counter() - t0,
        rotation=R,
    )
