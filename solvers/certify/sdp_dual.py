"""Dual certificates of a candidate solution, found by Douglas-Rachford splitting.

For the dense (QUASAR) relaxation of an arrowhead :class:`~solvers.certify.relaxation.Lifting` and a
rank-one candidate ``x = [y; theta_1 y; ...; theta_K y]``, a dual certificate is a dual matrix
``S = C - blkdiag(D_0..D_K) - W`` (``W`` with skew off-diagonal blocks, ``sum_k D_k`` in the span
of the pose constraints) with ``S x = 0`` and ``S >= 0``. The affine conditions form a set ``A``;
Douglas-Rachford alternates the projection onto ``A`` (a least-norm correction whose normal
matrix is factored once per candidate) and onto the PSD cone (one eigendecomposition). This
follows the idea of TEASER++'s certifier (Yang, Shi, Carlone 2020), written for any arrowhead
lifting.

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
from solvers.lie import project_to_so3

__all__ = ["DualCertificateResult", "dual_certificate", "rotation_dual_certificate"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DualCertificateResult:
    """Outcome of a dual certificate search (:func:`dual_certificate`,
    :func:`rotation_dual_certificate`, :func:`solvers.certify.joint_dual.joint_dual_certificate`).

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


def _sym_basis(d: int) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.int64]]:
    """Orthonormal basis of symmetric d x d matrices: (m, d, d) and the index pairs."""
    ia, ib = np.triu_indices(d)
    E = np.zeros((ia.size, d, d))
    s = np.where(ia == ib, 1.0, 1 / np.sqrt(2))
    E[np.arange(ia.size), ia, ib] = s
    E[np.arange(ia.size), ib, ia] = s
    return E, ia, ib


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


class _AffineProjector:
    """Projection onto ``{S = S_base + sum z_m E_m : L z = r}`` for one candidate."""

    def __init__(self, lift: Lifting, x: NDArray[np.float64]) -> None:
        import scipy.sparse as sp

        K, d = lift.K, lift.d
        nb = K + 1
        self.K, self.d, self.nb = K, d, nb
        n = d * nb
        xb = x.reshape(nb, d)
        Es, ia, ib = _sym_basis(d)
        ms = Es.shape[0]
        self.ia, self.ib = ia, ib
        self.sym_scale = np.where(ia == ib, 1.0, np.sqrt(2))
        # Skew pairs (a < b) and block pairs (i < j).
        sa, sb = np.triu_indices(d, 1)
        self.sa, self.sb = sa, sb
        bi, bj = np.triu_indices(nb, 1)
        self.bi, self.bj = bi, bj
        mw = sa.size
        # Base: C off-diagonal blocks (symmetric) and C_00.
        S0 = lift.dense_cost()
        self.S_base = S0
        rows, cols, vals = [], [], []
        # P_i coordinates: column index i * ms + m; E_m x_i lands in block row i.
        Ex = np.einsum("mab,ib->ima", Es, xb)  # (nb, ms, d)
        ii, mm, aa = np.meshgrid(np.arange(nb), np.arange(ms), np.arange(d), indexing="ij")
        rows.append((ii * d + aa).ravel())
        cols.append((ii * ms + mm).ravel())
        vals.append(Ex.ravel())
        off = nb * ms
        # W_ij coordinate (a, b): block (i, j) gets (e_ab - e_ba) / 2, block (j, i) the negative.
        # Row block i: 0.5 (e_ab - e_ba) x_j ; row block j: -0.5 (e_ab - e_ba) x_i.
        npair = bi.size
        p_idx = np.arange(npair)[:, None]
        s_idx = np.arange(mw)[None, :]
        col = off + p_idx * mw + s_idx  # (npair, mw)
        for blk_row, other, sign in ((bi, bj, 0.5), (bj, bi, -0.5)):
            xo = xb[other]  # (npair, d)
            # (e_ab - e_ba) x: entry a gets x_b, entry b gets -x_a.
            rows.append((blk_row[:, None] * d + sa[None, :]).ravel())
            cols.append(col.ravel())
            vals.append((sign * xo[:, sb]).ravel())
            rows.append((blk_row[:, None] * d + sb[None, :]).ravel())
            cols.append(col.ravel())
            vals.append((-sign * xo[:, sa]).ravel())
        # Product constraints <A_l, Z_ij> = 0 (homogeneous pose constraints): their multipliers
        # add a symmetric part spanned by an orthonormal basis H of those A_l to each pair block.
        hom = lift.eq_mats[lift.eq_rhs == 0].reshape(-1, d * d)
        if hom.shape[0]:
            u, sv, _ = np.linalg.svd(hom.T, full_matrices=False)
            H = u[:, sv > sv.max() * 1e-10].T.reshape(-1, d, d)
        else:
            H = np.zeros((0, d, d))
        mh = H.shape[0]
        self.H, self.mh = H, mh
        offh = off + npair * mw
        if mh:
            colh = offh + p_idx * mh + np.arange(mh)[None, :]  # (npair, mh)
            for blk_row, other in ((bi, bj), (bj, bi)):
                Hx = np.einsum("mab,pb->pma", H, xb[other]) / np.sqrt(2)  # (npair, mh, d)
                rows.append(np.broadcast_to((blk_row[:, None, None] * d
                                             + np.arange(d)[None, None, :]), Hx.shape).ravel())
                cols.append(np.broadcast_to(colh[:, :, None], Hx.shape).ravel())
                vals.append(Hx.ravel())
        nvar = offh + npair * mh
        self.offh = offh
        self.nvar, self.off, self.ms, self.mw = nvar, off, ms, mw
        Lx = sp.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, nvar)
        )
        # sum_k P_k must lie in span(eq_mats): its component orthogonal to the span vanishes.
        A = np.einsum("lab,mab->lm", lift.eq_mats, Es)  # svec coordinates of the span
        Q, _ = np.linalg.qr(np.concatenate([A.T, np.eye(ms)], axis=1))
        rank = np.linalg.matrix_rank(A) if A.size else 0
        U = Q[:, rank:ms]  # orthonormal complement, (ms, ms - rank)
        Ls = sp.csr_matrix(np.tile(U.T, (1, nb)))
        Ls = sp.hstack([Ls, sp.csr_matrix((U.shape[1], nvar - off))])
        self.L = sp.vstack([Lx, Ls]).tocsr()
        # Right-hand side: S_base x + L z = 0 and U^T svec(C_00 + sum P) = 0.
        self.r = np.concatenate([-(S0 @ x), np.zeros(U.shape[1])])
        G = (self.L @ self.L.T).toarray()
        w, V = np.linalg.eigh(G)
        keep = w > w.max() * 1e-12
        self.Ginv_V = V[:, keep] / w[keep]
        self.V = V[:, keep]
        self.Es = Es

    def coords(self, M: NDArray[np.float64]) -> NDArray[np.float64]:
        d, nb = self.d, self.nb
        blk = M.reshape(nb, d, nb, d).transpose(0, 2, 1, 3)
        diag = blk[np.arange(nb), np.arange(nb)]  # (nb, d, d)
        base_diag = self.S_base[:d, :d]
        diag = diag.copy()
        diag[0] -= base_diag
        zp = 0.5 * (diag[:, self.ia, self.ib] + diag[:, self.ib, self.ia]) * self.sym_scale
        ob = blk[self.bi, self.bj]  # (npair, d, d)
        zw = ob[:, self.sa, self.sb] - ob[:, self.sb, self.sa]
        # <E_w, M> with E_w = (e_ab - e_ba)/2 in block (i,j) and its negative transposed in (j,i)
        if not self.mh:
            return np.concatenate([zp.ravel(), zw.ravel()])
        cb = self.S_base.reshape(nb, d, nb, d).transpose(0, 2, 1, 3)[self.bi, self.bj]
        zh = np.sqrt(2) * np.einsum("mab,pab->pm", self.H, ob - cb)
        return np.concatenate([zp.ravel(), zw.ravel(), zh.ravel()])

    def matrix(self, z: NDArray[np.float64]) -> NDArray[np.float64]:
        d, nb = self.d, self.nb
        S = self.S_base.copy()
        blk = S.reshape(nb, d, nb, d).transpose(0, 2, 1, 3)  # view
        zp = z[: self.off].reshape(nb, self.ms)
        P = np.einsum("im,mab->iab", zp, self.Es)
        idx = np.arange(nb)
        blk[idx, idx] += P
        zw = z[self.off:self.offh].reshape(-1, self.mw) / 2
        W = np.zeros((self.bi.size, d, d))
        W[:, self.sa, self.sb] = zw
        W[:, self.sb, self.sa] = -zw
        if self.mh:
            W += np.einsum("pm,mab->pab", z[self.offh:].reshape(-1, self.mh), self.H) / np.sqrt(2)
        blk[self.bi, self.bj] += W
        blk[self.bj, self.bi] += np.swapaxes(W, 1, 2)
        return S

    def project(self, M: NDArray[np.float64]) -> NDArray[np.float64]:
        z = self.coords(M)
        res = self.L @ z - self.r
        z = z - self.L.T @ (self.Ginv_V @ (self.V.T @ res))
        return self.matrix(z)


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


def dual_certificate(
    lift: Lifting,
    x: NDArray[np.float64],
    *,
    tol: float = 1e-3,
    max_iterations: int = 500,
    check_every: int = 10,
    time_limit: float | None = None,
    relaxation: float = 1.0,
    anderson: int = 0,
) -> DualCertificateResult:
    """Search a dual certificate of the rank-one candidate ``x`` (length ``d (K + 1)``).

    Parameters
    ----------
    lift : Lifting
    x : (d (K + 1),) ndarray
        Lifted candidate; ``x[:d]`` must satisfy the pose constraints.
    tol : float
        Target relative gap ``(x^T C x - lb) / (1 + |x^T C x| + |lb|)``.
    max_iterations : int
        Douglas-Rachford iterations.
    check_every : int
        Iterations between two (eigendecomposition-costly) bound evaluations.
    time_limit : float or None
        Seconds after which the iteration stops.
    relaxation : float
        Over-relaxation of the Douglas-Rachford step, in (0, 2).
    anderson : int
        Memory of the Anderson acceleration (0: off).
    """
    t0 = time.perf_counter()
    C = lift.dense_cost()
    f = float(x @ C @ x)

    def rel(lb: float) -> float:
        return (f - lb) / (1 + abs(f) + abs(lb))

    proj = _AffineProjector(lift, x)

    def step(M: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """One relaxed Douglas-Rachford step: the residual T(M) - M and the affine point."""
        P = _psd_part(M)
        S = proj.project(2 * P - M)
        return relaxation * (S - P), S

    best_lb, best_eig, it, conv = -np.inf, np.nan, 0, False
    for it, S in _drs_iterates(step, proj.project(np.zeros_like(C)), max_iterations, anderson):
        if it and (it % check_every == 0 or it == max_iterations):
            lb, lam = bound_from_dense_dual(lift, S)
            if lb > best_lb:
                best_lb, best_eig = lb, lam
            if rel(best_lb) <= tol:
                conv = True
                break
            if time_limit is not None and time.perf_counter() - t0 > time_limit:
                break
    return DualCertificateResult(
        lower_bound=float(best_lb),
        upper_bound=f,
        min_eig=float(best_eig),
        iterations=it,
        converged=conv,
        solve_time=time.perf_counter() - t0,
    )


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
        from solvers.certify._kernels import identity_frame_projection

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


def _psd_part_few(M: NDArray[np.float64], m: int = 8) -> NDArray[np.float64]:
    """Projection onto the PSD cone when ``M`` has few negative eigenvalues.

    Only the ``m`` smallest eigenpairs are computed (LAPACK ``evr`` with an index range: 1.4x
    faster than a full ``eigh`` at n = 84, 2.8x at n = 404); if all ``m`` are negative, the
    full decomposition is used. Near a certificate ``M`` has at most 4-5 (measured).
    """
    from scipy.linalg import eigh

    n = M.shape[0]
    if n <= 2 * m:
        return _psd_part(M)
    w, V = eigh(M, subset_by_index=[0, m - 1], driver="evr", check_finite=False)
    if w[-1] < 0:
        return _psd_part(M)
    neg = w < 0
    if not neg.any():
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

    def rel(lb: float, f: float) -> float:
        return (f - lb) / (1 + abs(f) + abs(lb))

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
            delta = 0.5 * tol * (1 + 2 * abs(f)) / (nb * (1 + tol))
            M, local, R_new, S = S_init, 0, None, S_init
            done = _is_pd(S_init, delta)
            while not done and it < max_iterations:
                it += 1
                local += 1
                P = _psd_part_few(M)
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
