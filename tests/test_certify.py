"""Certificates: soundness against exhaustive search, tightness, refusals and failure paths."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from solvers import solve_registration
from solvers.certificate import CertificateStatus
from solvers.certify import (
    certify_pose,
    certify_result,
    certify_rotation,
    refine_rotation,
    rotation_gnc,
    solve_sdp,
)
from solvers.certify.relaxation import RotationTLSProblem, joint_lifting, rotation_lifting
from solvers.certify.sdp_relaxation import bound_from_dense_dual, solve_relaxation
from solvers.lie import rotation_error_deg
from solvers.problem import WeightedTLSProblem
from solvers.procrustes import weighted_procrustes, weighted_rotation
from tests.conftest import make_instance


# ----------------------------------------------------------------------------- exhaustive optima
def _subsets(k: int) -> np.ndarray:
    return ((np.arange(1 << k)[:, None] >> np.arange(k)[None, :]) & 1).astype(bool)


def rotation_optimum(p: RotationTLSProblem) -> float:
    """Exact optimum: min over inlier sets S of [LS cost on S + cbar2 * weight outside S]."""
    w = p.weights / p.noise_bound**2
    best = p.cbar2 * p.weights.sum()  # S empty
    for S in _subsets(p.n)[1:]:
        R = weighted_rotation((p.target[S] * w[S, None]).T @ p.source[S])
        c = float(p.weights[S] @ p.residuals_sq(R)[S] + p.cbar2 * p.weights[~S].sum())
        best = min(best, c)
    return best


def full_optimum(p: WeightedTLSProblem) -> float:
    w = p.weights / p.noise_bound**2
    best = p.cbar2 * p.weights.sum()
    for S in _subsets(p.n)[1:]:
        if not np.any(w[S] > 0):
            continue
        R, t = weighted_procrustes(p.source[S], p.target[S], w[S])
        c = float(p.weights[S] @ p.residuals_sq(R, t)[S] + p.cbar2 * p.weights[~S].sum())
        best = min(best, c)
    return best


def random_rotation_problem(rng: np.random.Generator, k: int, n_out: int,
                            *, sigma: float = 0.01, varied: bool = True) -> tuple[
                                RotationTLSProblem, np.ndarray]:
    R = Rotation.random(random_state=rng).as_matrix()
    a = rng.uniform(-1, 1, (k, 3))
    b = a @ R.T + sigma * rng.normal(size=(k, 3))
    b[:n_out] = rng.normal(size=(n_out, 3))
    beta = 5.54 * sigma * (rng.uniform(0.7, 1.5, k) if varied else np.ones(k))
    w = rng.uniform(0.3, 2.0, k) if varied else None
    c2 = float(rng.uniform(0.5, 2.0)) if varied else 1.0
    return RotationTLSProblem(a, b, noise_bound=beta, weights=w, cbar2=c2), R


# ----------------------------------------------------------------------------- soundness
@pytest.mark.parametrize("method", [pytest.param("dense", marks=pytest.mark.slow), "dual"])
def test_soundness_rotation_against_exhaustive_search(method: str) -> None:
    """100 + 100 instances, K <= 8: bound <= optimum always; certified => globally optimal."""
    rng = np.random.default_rng(7 if method == "dense" else 8)
    n_cert = 0
    for i in range(100):
        k = int(rng.integers(4, 7 if method == "dense" else 9))
        n_out = int(rng.integers(0, k - 1))
        p, _ = random_rotation_problem(rng, k, n_out, varied=i % 2 == 0)
        opt = rotation_optimum(p)
        # Alternate a good candidate (GNC) and a random one: the bound must hold for both.
        R = rotation_gnc(p) if i % 3 else Rotation.random(random_state=rng).as_matrix()
        cert = certify_rotation(p, R, method=method, max_iter=200 if method == "dense" else 400)
        scale = 1.0 + p.cbar2 * p.weights.sum()
        assert cert.lower_bound <= opt + 1e-6 * scale, (i, cert, opt)
        assert cert.upper_bound == pytest.approx(p.cost(R))
        if cert.certified:
            n_cert += 1
            assert cert.upper_bound - opt <= cert.tol * (1 + abs(cert.upper_bound) + abs(opt))
    assert n_cert >= 40  # the relaxation is tight on most of these


def test_bound_is_valid_for_arbitrary_dual_points() -> None:
    """The recomputed bound holds for garbage dual matrices too (eigenvalue correction)."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        p, _ = random_rotation_problem(rng, 5, 2)
        lift = rotation_lifting(p)
        n = lift.d * (lift.K + 1)
        G = rng.normal(size=(n, n)) * rng.uniform(0.01, 100)
        lb, _ = bound_from_dense_dual(lift, G + G.T)
        assert lb <= rotation_optimum(p) + 1e-9


@pytest.mark.slow  # over 3 s
def test_soundness_full_problem_chordal() -> None:
    """Joint rotation-translation relaxation (chordal) bounds the full problem's optimum."""
    rng = np.random.default_rng(11)
    for _ in range(3):
        src, dst, *_ = make_instance(rng, 5, 0.4)
        p = WeightedTLSProblem(src, dst, noise_bound=0.0554)
        sol = solve_relaxation(joint_lifting(p), kind="chordal")
        assert sol.status in ("solved", "inaccurate") and np.isfinite(sol.lower_bound)
        assert sol.lower_bound <= full_optimum(p) + 1e-6 * (1 + p.n)


@pytest.mark.slow
def test_dense_joint_relaxation_is_tight_and_sound() -> None:
    """Dense joint relaxation with product constraints: tight on a small instance."""
    rng = np.random.default_rng(5)
    src, dst, *_ = make_instance(rng, 4, 0.25)
    p = WeightedTLSProblem(src, dst, noise_bound=0.0554)
    res = solve_sdp(p, scope="full", method="dense", eps=1e-6)
    opt = full_optimum(p)
    cert = res.certificate
    assert cert is not None and cert.problem == "full_weighted_tls"
    assert cert.lower_bound <= opt + 1e-6 * (1 + p.n)
    assert cert.certified
    assert res.cost <= opt + 1e-3 * (1 + opt)


# ----------------------------------------------------------------------------- tightness
def test_noiseless_exact_recovery_and_rank_one() -> None:
    rng = np.random.default_rng(2)
    R_gt = Rotation.random(random_state=rng).as_matrix()
    a = rng.uniform(-1, 1, (8, 3))
    b = a @ R_gt.T  # noiseless inliers
    b[:2] = rng.normal(size=(2, 3))
    p = RotationTLSProblem(a, b, noise_bound=0.01)
    sol = solve_relaxation(rotation_lifting(p), kind="dense")
    assert sol.status == "solved"
    assert sol.eigenvalue_ratio > 1e4  # rank one
    assert sol.lower_bound == pytest.approx(2.0, abs=1e-5)  # two outliers at cbar2 = 1
    w, V = np.linalg.eigh(sol.Z00)
    from solvers.certify.relaxation import quaternion_to_rotation

    assert rotation_error_deg(quaternion_to_rotation(V[:, -1]), R_gt) < 1e-3


def test_solve_sdp_recovers_noiseless_pose_with_certificate() -> None:
    rng = np.random.default_rng(4)
    src, dst, R, t, _ = make_instance(rng, 12, 0.25, sigma=1e-9)
    p = WeightedTLSProblem(src, dst, noise_bound=0.01)
    res = solve_sdp(p)
    assert res.success and res.solver == "sdp"
    assert rotation_error_deg(res.rotation, R) < 1e-3
    assert np.linalg.norm(res.translation - t) < 1e-4
    assert res.certificate is not None and res.certificate.certified
    assert res.certificate.problem == "rotation_tim_subproblem"


def test_certify_result_on_gnc_candidate() -> None:
    rng = np.random.default_rng(9)
    src, dst, R, t, _ = make_instance(rng, 20, 0.5)
    p = WeightedTLSProblem(src, dst, noise_bound=0.0554)
    res = certify_result(p, solve_registration(p))
    cert = res.certificate
    assert cert is not None and cert.certified, cert
    assert cert.status is CertificateStatus.CERTIFIED
    assert rotation_error_deg(res.rotation, R) < 5


# ----------------------------------------------------------------------------- refusals
@pytest.mark.parametrize("deg", [3.0, 10.0, 30.0])
@pytest.mark.parametrize(("method", "k"), [("dual", 20), ("dense", 8)])
def test_wrong_candidate_is_not_certified(deg: float, method: str, k: int) -> None:
    rng = np.random.default_rng(int(deg))
    p, _ = random_rotation_problem(rng, k, int(0.4 * k), varied=False)
    R_opt = rotation_gnc(p)
    good = certify_rotation(p, R_opt, method=method)
    assert good.certified, good
    axis = rng.normal(size=3)
    R_bad = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix() @ R_opt
    bad = certify_rotation(p, R_bad, method=method)
    assert not bad.certified
    assert bad.status is CertificateStatus.GAP_TOO_LARGE  # the bound is tight, the pose is not
    assert "candidate is suboptimal" in bad.message  # and the user learns a better one exists
    assert bad.lower_bound <= good.upper_bound + 1e-6 * (1 + p.n)


def test_wrong_full_pose_is_not_certified() -> None:
    rng = np.random.default_rng(12)
    src, dst, R, t, _ = make_instance(rng, 20, 0.3)
    p = WeightedTLSProblem(src, dst, noise_bound=0.0554)
    res = solve_registration(p)
    R_bad = Rotation.from_rotvec(np.radians(10.0) * np.array([0.0, 0.0, 1.0])).as_matrix() @ res.rotation
    cert = certify_pose(p, R_bad, res.translation)  # default: the full problem
    assert not cert.certified and cert.problem == "full_weighted_tls"
    assert cert.status is CertificateStatus.GAP_TOO_LARGE
    tim = certify_pose(p, R_bad, res.translation, scope="rotation")
    assert not tim.certified and tim.problem == "rotation_tim_subproblem"


# ----------------------------------------------------------------------------- failure paths
def test_iteration_limit_gives_uncertified_status() -> None:
    rng = np.random.default_rng(1)
    p, _ = random_rotation_problem(rng, 6, 2)
    cert = certify_rotation(p, rotation_gnc(p), method="dense", max_iter=1)
    assert not cert.certified
    assert cert.status is CertificateStatus.ITERATION_LIMIT
    assert "max" in cert.backend_status.lower() or "limit" in cert.backend_status.lower()


def test_dual_search_iteration_limit() -> None:
    rng = np.random.default_rng(1)
    p, _ = random_rotation_problem(rng, 20, 10)
    cert = certify_rotation(p, rotation_gnc(p), method="dual", max_iter=1)
    assert not cert.certified
    assert cert.status is CertificateStatus.ITERATION_LIMIT
    assert cert.lower_bound <= cert.upper_bound + 1e-9


def test_malformed_candidates() -> None:
    rng = np.random.default_rng(0)
    src, dst, *_ = make_instance(rng, 10, 0.2)
    p = WeightedTLSProblem(src, dst, noise_bound=0.05)
    cert = certify_pose(p, np.full((3, 3), np.nan), np.zeros(3))
    assert not cert.certified and cert.status is CertificateStatus.INVALID_INPUT
    cert = certify_pose(p, 2 * np.eye(3), np.zeros(3))
    assert cert.status is CertificateStatus.INVALID_INPUT
    with pytest.raises(ValueError, match="`R`"):
        certify_pose(p, np.eye(4), np.zeros(3))
    with pytest.raises(ValueError, match="`tol`"):
        certify_pose(p, np.eye(3), np.zeros(3), tol=0.0)
    with pytest.raises(ValueError, match="`scope`"):
        certify_pose(p, np.eye(3), np.zeros(3), scope="everything")  # type: ignore[arg-type]


def test_sdp_failure_is_reported_not_raised() -> None:
    rng = np.random.default_rng(6)
    src, dst, *_ = make_instance(rng, 8, 0.25)
    p = WeightedTLSProblem(src, dst, noise_bound=0.05)
    res = solve_sdp(p, max_iter=1)
    assert not res.success and "did not reach its tolerances" in res.message
    # The rounded pose's certificate comes from its own dual search, independent of the failed
    # interior-point solve: valid whatever the verdict.
    cert = res.certificate
    assert cert is not None and cert.method == "dual_drs"
    from solvers.certify import rebuild_bounded_problem

    assert cert.lower_bound <= rotation_optimum(rebuild_bounded_problem(p, cert)) + 1e-9


def test_refine_rotation_never_increases_cost() -> None:
    rng = np.random.default_rng(10)
    p, _ = random_rotation_problem(rng, 15, 5)
    for _ in range(10):
        R0 = Rotation.random(random_state=rng).as_matrix()
        assert p.cost(refine_rotation(p, R0)) <= p.cost(R0) + 1e-12


# ----------------------------------------------------------------------------- API and CLI
def test_register_with_certify() -> None:
    import certpose

    rng = np.random.default_rng(13)
    src, dst, R, t, _ = make_instance(rng, 20, 0.4)
    res = certpose.register(src, dst, noise_bound=0.0554, certify=True)
    assert res.certificate is not None and res.certificate.certified
    assert res.certificate.to_dict()["status"] == "certified"
    res = certpose.register(src, dst, noise_bound=0.0554, solver="sdp")
    assert res.solver == "sdp" and res.certificate is not None


def test_cli_register_prints_certificate(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    from certpose.cli import main

    rng = np.random.default_rng(14)
    src, dst, *_ = make_instance(rng, 20, 0.3)
    np.savetxt(tmp_path / "src.xyz", src)
    np.savetxt(tmp_path / "dst.xyz", dst)
    code = main(["register", str(tmp_path / "src.xyz"), str(tmp_path / "dst.xyz"),
                 "--noise-bound", "0.0554", "--certify"])
    out = capsys.readouterr().out.lower()
    assert code == 0
    assert "certif" in out and "gap" in out


@pytest.mark.parametrize("kind", ["dense", "chordal"])
def test_infeasible_relaxation_is_reported_not_raised(kind: str) -> None:
    """``tr(Z_00) = -1`` has no PSD solution: the backend's verdict reaches the certificate."""
    import dataclasses

    from solvers.certificate import BoundedProblem
    from solvers.certify.front import _finish_certificate, _ipm_bound, _Scoped

    rng = np.random.default_rng(4)
    p, _ = random_rotation_problem(rng, 5, 1)
    lift = dataclasses.replace(rotation_lifting(p), eq_rhs=-np.ones(1))
    sol = solve_relaxation(lift, kind=kind)  # type: ignore[arg-type]
    assert sol.status == "infeasible" and not sol.accepted, sol
    bound = _ipm_bound(lift, kind, 200, 1e-7)
    assert bound.status is CertificateStatus.INFEASIBLE and not bound.accepted
    cert = _finish_certificate(p.cost(np.eye(3)), bound, tol=1e-3, ws=1.0, outlier_cost=0.0,
                               scoped=_Scoped(BoundedProblem.ROTATION, p, None, None), t0=0.0)
    assert not cert.certified and cert.status is CertificateStatus.INFEASIBLE
    assert "no certificate" in cert.message


def test_full_scope_joint_dual_search() -> None:
    """method="dual": the joint dual search certifies the full problem as a whole."""
    rng = np.random.default_rng(14)
    src, dst, R, t, _ = make_instance(rng, 8, 0.0)
    p = WeightedTLSProblem(src, dst, noise_bound=0.0554)
    res = solve_registration(p)
    cert = certify_pose(p, res.rotation, res.translation, scope="full", method="dual",
                        time_limit=60)
    assert cert.problem == "full_weighted_tls" and cert.method == "dual_drs"
    assert cert.certified, cert
    assert cert.lower_bound <= full_optimum(p) + 1e-6 * (1 + p.weights.sum())
