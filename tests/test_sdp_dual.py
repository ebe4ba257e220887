"""The identity-frame dual certificate search of the quaternion relaxation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from solvers.certify import refine_rotation, rotation_gnc
from solvers.certify.relaxation import RotationTLSProblem, rotation_lifting
from solvers.certify.sdp_dual import (
    _IdentityFrameProjector,
    _NegativePart,
    _psd_part,
    _rotation_initial_dual,
    rotation_dual_certificate,
)
from tests.test_certify import random_rotation_problem, rotation_optimum


def _identity_frame(p: RotationTLSProblem, R: np.ndarray):  # noqa: ANN202
    b = p.target @ R
    ident = RotationTLSProblem(p.source, b, noise_bound=p.noise_bound, weights=p.weights,
                               cbar2=p.cbar2)
    theta = np.where(ident.inliers(np.eye(3)), 1.0, -1.0)
    beta = p.noise_bound[:, None]
    a = p.source / beta
    f = ident.cost(np.eye(3))
    S = _rotation_initial_dual(rotation_lifting(ident), a, b / beta - a, theta, p.weights,
                               p.cbar2, f)
    nb = p.n + 1
    S = S.transpose(0, 2, 1, 3).reshape(4 * nb, 4 * nb)
    th = np.concatenate([[1.0], theta])
    return ident, S, th, f


def _dual_structure_residual(ident: RotationTLSProblem, S: np.ndarray, f: float) -> float:
    """Distance of S from the form C - blkdiag(D) - W, sum D = f I, W skew (identity frame)."""
    lift = rotation_lifting(ident)
    nb = lift.K + 1
    G = (lift.dense_cost() - S).reshape(nb, 4, nb, 4).transpose(0, 2, 1, 3)
    off = ~np.eye(nb, dtype=bool)
    sym_off = np.abs(G[off] + np.swapaxes(G[off], 1, 2)).max()
    diag_sum = np.einsum("kkab->ab", G)
    return float(max(sym_off, np.abs(diag_sum - f * np.eye(4)).max()))


@pytest.mark.parametrize("seed", range(5))
def test_initial_dual_point_is_structured_and_stationary(seed: int) -> None:
    rng = np.random.default_rng(seed)
    p, _ = random_rotation_problem(rng, 12, 4)
    R = refine_rotation(p, rotation_gnc(p))
    ident, S, th, f = _identity_frame(p, R)
    assert _dual_structure_residual(ident, S, f) < 1e-9 * (1 + f)
    x = np.kron(th, [0.0, 0.0, 0.0, 1.0])
    # A refined candidate is stationary, so the closed-form point has x in its kernel.
    assert np.abs(S @ x).max() < 1e-7 * (1 + np.abs(S).max())


@pytest.mark.parametrize("seed", range(5))
def test_projection_is_the_orthogonal_projection_onto_the_affine_set(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    p, _ = random_rotation_problem(rng, 9, 3)
    R = refine_rotation(p, rotation_gnc(p))
    ident, S0, th, f = _identity_frame(p, R)
    proj = _IdentityFrameProjector(S0, th)
    n = S0.shape[0]
    x = np.kron(th, [0.0, 0.0, 0.0, 1.0])
    M1, M2 = (G + G.T for G in rng.normal(size=(2, n, n)))
    P1, P2 = proj(M1), proj(M2)
    for P in (P1, P2):
        assert _dual_structure_residual(ident, P, f) < 1e-9 * (1 + np.abs(P).max())
        assert np.abs(P @ x - S0 @ x).max() < 1e-9 * (1 + np.abs(P).max())  # D x = 0
        np.testing.assert_allclose(P, P.T, atol=1e-12)
    np.testing.assert_allclose(proj(P1), P1, atol=1e-10)  # idempotent
    # Orthogonal: the residual M - P(M) is normal to every direction inside the set.
    assert abs(np.sum((M1 - P1) * (P2 - P1))) < 1e-8 * np.linalg.norm(M1) * np.linalg.norm(P2)


def test_bound_is_sound_for_any_candidate() -> None:
    """Random, perturbed and good candidates: the recomputed bound never exceeds the optimum."""
    rng = np.random.default_rng(21)
    for i in range(60):
        k = int(rng.integers(4, 9))
        p, _ = random_rotation_problem(rng, k, int(rng.integers(0, k - 1)), varied=i % 2 == 0)
        opt = rotation_optimum(p)
        R_good = rotation_gnc(p)
        R = (R_good, Rotation.random(random_state=rng).as_matrix(), Rotation.from_rotvec(rng.normal(scale=0.2, size=3)).as_matrix() @ R_good)[i % 3]
        res = rotation_dual_certificate(p, R, max_iterations=50)
        assert res.lower_bound <= opt + 1e-6 * (1 + p.cbar2 * p.weights.sum()), (i, res, opt)
        assert res.upper_bound == pytest.approx(p.cost(res.rotation))
        assert res.upper_bound <= p.cost(R) + 1e-12  # restarts only ever improve
        if res.converged:
            assert res.upper_bound - opt <= 1e-3 * (1 + abs(res.upper_bound) + abs(opt))


@pytest.mark.parametrize(("k", "ratio"), [(30, 0.0), (30, 0.5), (60, 0.8)])
def test_weighted_instances_certify_in_few_iterations(k: int, ratio: float) -> None:
    """Uneven weights and noise bounds: the closed-form start is scaled per term."""
    rng = np.random.default_rng(k)
    p, _ = random_rotation_problem(rng, k, int(ratio * k), varied=True)
    R = rotation_gnc(p)
    res = rotation_dual_certificate(p, R)
    assert res.converged, res
    assert res.iterations <= 30
    assert res.lower_bound <= res.upper_bound + 1e-9


@pytest.mark.parametrize("deg", [3.0, 10.0, 30.0])
def test_rotated_candidate_is_refused(deg: float) -> None:
    """The bound refuses the rotated pose; the search moves on to the optimum and certifies it."""
    rng = np.random.default_rng(int(deg) + 1)
    p, _ = random_rotation_problem(rng, 50, 25, varied=False)
    R = rotation_gnc(p)
    axis = rng.normal(size=3)
    R_bad = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix() @ R
    res = rotation_dual_certificate(p, R_bad, restart_every=0, max_iterations=30)
    assert not res.converged
    assert res.lower_bound <= p.cost(R) + 1e-6 * (1 + p.n)
    res = rotation_dual_certificate(p, R_bad)
    gap_bad = (p.cost(R_bad) - res.lower_bound) / (1 + p.cost(R_bad) + abs(res.lower_bound))
    assert gap_bad > 1e-3
    assert res.converged and res.upper_bound <= p.cost(R) + 1e-9 * (1 + p.cost(R))


def test_restarts_reach_the_global_optimum_from_local_minima() -> None:
    """Candidates refined from random rotations (local minima): rounding the dual's negative
    directions leads to the exhaustive-search optimum, which is then certified."""
    rng = np.random.default_rng(3)
    tried = 0
    for _ in range(30):
        p, _ = random_rotation_problem(rng, 10, 4, varied=False)
        opt = rotation_optimum(p)
        R0 = refine_rotation(p, Rotation.random(random_state=rng).as_matrix())
        if p.cost(R0) <= opt + 1e-6 * (1 + opt):
            continue  # already optimal
        tried += 1
        res = rotation_dual_certificate(p, R0)
        assert res.lower_bound <= opt + 1e-6 * (1 + opt)
        assert res.rotation is not None and res.upper_bound == pytest.approx(p.cost(res.rotation))
        assert res.converged and res.upper_bound <= opt + 1e-6 * (1 + opt), res
    assert tried >= 20


def test_compiled_projection_matches_numpy_reference() -> None:
    rng = np.random.default_rng(5)
    p, _ = random_rotation_problem(rng, 15, 6)
    R = refine_rotation(p, rotation_gnc(p))
    _, S0, th, _ = _identity_frame(p, R)
    proj = _IdentityFrameProjector(S0, th)
    for _ in range(3):
        G = rng.normal(size=S0.shape)
        M = G + G.T
        np.testing.assert_allclose(proj(M), proj.reference(M), rtol=1e-12, atol=1e-10)


@pytest.mark.parametrize("n", [40, 100, 432])
def test_negative_part_projection_equals_the_full_decomposition(n: int) -> None:
    """The projection from the negative eigenpairs only is the full one, whether the iterates
    have few negative eigenvalues (LAPACK's evr over them) or many (the full decomposition,
    chosen from the previous iterate's count), and counts them."""
    rng = np.random.default_rng(n)
    project = _NegativePart()
    for neg in (3, n // 3, n // 3, 5, 0):
        Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        w = rng.uniform(0.1, 2.0, n)
        w[:neg] *= -1
        M = (Q * w) @ Q.T
        M = (M + M.T) / 2
        P = project(M)
        np.testing.assert_allclose(P, _psd_part(M), atol=1e-10)
        assert np.linalg.eigvalsh(P)[0] > -1e-10
        assert project.count == neg


def test_bad_arguments_are_refused_with_their_name() -> None:
    rng = np.random.default_rng(0)
    p, _ = random_rotation_problem(rng, 6, 1)
    with pytest.raises(ValueError, match="`R`"):
        rotation_dual_certificate(p, np.eye(4))
    with pytest.raises(ValueError, match="`R`"):
        rotation_dual_certificate(p, np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="`R` to be a rotation"):
        rotation_dual_certificate(p, 2 * np.eye(3))  # a non-rotation would bound another problem
    with pytest.raises(ValueError, match="`tol`"):
        rotation_dual_certificate(p, np.eye(3), tol=0.0)
    with pytest.raises(ValueError, match="`relaxation`"):
        rotation_dual_certificate(p, np.eye(3), relaxation=2.0)
    with pytest.raises(ValueError, match="`max_iterations`"):
        rotation_dual_certificate(p, np.eye(3), max_iterations=-1)
