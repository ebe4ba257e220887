"""Certificates on real FPFH correspondences (the shared 3DMatch pair, as the bench suite builds
them): ``register(certify=True)`` returns a certified statement about its own pose, and the
certificate says which problem it bounds."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose import register
from certpose.bench.suites import ROTATION_TOL_DEG, THREEDMATCH_TRANSLATION_TOL
from certpose.data.threedmatch import threedmatch_correspondences
from solvers.certify import rebuild_bounded_problem
from solvers.certify.front import refine_translation
from solvers.certify.relaxation import RotationTLSProblem
from solvers.problem import WeightedTLSProblem
from solvers.result import SolverStatus
from tests.conftest import require_data


@pytest.fixture(scope="module")
def corr():
    return threedmatch_correspondences(require_data("3dmatch", "gt.npy").parent)


@pytest.mark.slow
@pytest.mark.parametrize("noise_bound", [0.05, 0.1])
def test_register_certifies_a_statement_about_its_own_pose(corr, noise_bound) -> None:
    """Within 10 s the full problem's maximal cliques are too many to list: the rotation
    subproblem over the max clique is certified for the returned pose's rotation (its cost on
    the rebuilt subproblem is the certificate's upper bound and within the gap of its lower
    bound), unless the pose search certified the full problem in the time left, for a pose
    then returned (never costlier than the solver's)."""
    gnc = register(corr.source, corr.target, noise_bound=noise_bound)
    res = register(corr.source, corr.target, noise_bound=noise_bound, certify=True,
                   time_limit=10.0)
    cert = res.certificate
    assert cert.certified, cert.message
    p = WeightedTLSProblem(corr.source, corr.target, noise_bound=noise_bound)
    if cert.problem == "full_weighted_tls":
        assert res.cost <= gnc.cost * (1 + 1e-12)
        assert res.info["rotation_certificate"]["certified"]
    else:
        assert cert.problem == "rotation_tim_subproblem"
        unit = float(np.abs(np.r_[corr.source.ravel(), corr.target.ravel()]).max())
        sub = rebuild_bounded_problem(p, cert)
        assert isinstance(sub, RotationTLSProblem)
        assert sub.cost(res.rotation) == pytest.approx(cert.upper_bound, rel=1e-9, abs=1e-12 * unit)
        assert cert.lower_bound <= cert.upper_bound
        full = res.info["full_problem_certificate"]
        assert full["problem"] == "full_weighted_tls" and not full["certified"]
    # Still a registration of the scans by the bench suite's success criterion.
    T = corr.T_target_source
    assert Rotation.from_matrix(T[:3, :3].T @ res.rotation).magnitude() < np.radians(ROTATION_TOL_DEG)
    assert np.linalg.norm(res.translation - T[:3, 3]) < THREEDMATCH_TRANSLATION_TOL
    assert res.cost == pytest.approx(p.cost(res.rotation, res.translation), rel=1e-9)
    if res.status is SolverStatus.CERTIFIER_POSE and res.cost > res.info["candidate_cost"]:
        # Returned for its certificate at a higher cost: the solver's pose is on record.
        assert np.asarray(res.info["candidate_T_target_source"]).shape == (4, 4)


@pytest.mark.slow
def test_a_cheaper_pose_certified_on_the_full_problem_replaces_the_subproblems(corr) -> None:
    """At 0.1 m the rotation subproblem's certified optimum costs 1.96 more on the full problem
    than the solver's pose, and the pose search, given the time, certifies the solver's pose
    globally optimal: that pose is returned with the full problem's certificate, the
    subproblem's certificate and pose on record."""
    beta = 0.1
    gnc = register(corr.source, corr.target, noise_bound=beta)
    res = register(corr.source, corr.target, noise_bound=beta, certify=True, time_limit=60.0)
    cert = res.certificate
    assert cert.certified and cert.problem == "full_weighted_tls", res.message
    assert res.status is SolverStatus.CERTIFIER_POSE and res.info["replaced_candidate"]
    assert res.cost <= gnc.cost * (1 + 1e-12)
    p = WeightedTLSProblem(corr.source, corr.target, noise_bound=beta)
    assert cert.upper_bound == pytest.approx(p.cost(res.rotation, res.translation), rel=1e-9)
    rot = res.info["rotation_certificate"]
    assert rot["certified"] and rot["problem"] == "rotation_tim_subproblem"
    sub_pose = np.asarray(res.info["subproblem_T_target_source"])
    assert p.cost(sub_pose[:3, :3], sub_pose[:3, 3]) > res.cost
    assert res.info["subproblem_cost"] == pytest.approx(p.cost(sub_pose[:3, :3], sub_pose[:3, 3]))
    assert "certified a cheaper pose" in res.message


@pytest.mark.slow
def test_prefer_cost_returns_the_cheaper_pose_the_pose_search_finds(corr) -> None:
    """At 0.05 m the full problem's optimum (908.052) lies below the solver's pose (908.083);
    with ``prefer="cost"`` the pose search finds it, and it is returned with the full
    problem's certificate (the solver's pose, whose gap stays above the tolerance, on record)."""
    beta = 0.05
    gnc = register(corr.source, corr.target, noise_bound=beta)
    res = register(corr.source, corr.target, noise_bound=beta, certify=True, time_limit=60.0,
                   prefer="cost")
    assert res.cost < gnc.cost - 1e-3
    assert res.status is SolverStatus.CERTIFIER_POSE and res.info["replaced_candidate"]
    assert res.info["candidate_cost"] == pytest.approx(gnc.cost, rel=1e-12)
    cand = np.asarray(res.info["candidate_T_target_source"])
    assert np.allclose(cand, gnc.T_target_source, atol=1e-9)
    cert = res.certificate
    assert cert.problem == "full_weighted_tls" and cert.certified, res.message
    p = WeightedTLSProblem(corr.source, corr.target, noise_bound=beta)
    assert cert.upper_bound == pytest.approx(p.cost(res.rotation, res.translation), rel=1e-9)
    assert cert.lower_bound <= res.cost


@pytest.mark.slow
def test_prefer_cost_never_returns_a_costlier_pose(corr) -> None:
    gnc = register(corr.source, corr.target, noise_bound=0.05)
    res = register(corr.source, corr.target, noise_bound=0.05, certify=True, time_limit=10.0,
                   prefer="cost")
    assert res.cost <= gnc.cost * (1 + 1e-12)
    assert "rotation_certificate" in res.info or res.certificate.problem == "rotation_tim_subproblem"
    with pytest.raises(ValueError, match="prefer"):
        register(corr.source, corr.target, noise_bound=0.05, certify=True, prefer="best")


def test_prefer_cost_does_not_search_a_rotation_certificate_it_could_not_use(corr) -> None:
    """At 0.05 m the solver's rotation is not the rotation subproblem's optimum (the
    subproblem's local solvers find a cheaper rotation) and that rotation's pose costs more on
    the full problem: with ``prefer="cost"`` the dual search, which could only refuse the
    candidate, is not run, and the full problem's pose search gets its time. The record says
    so, bounds the subproblem by 0 and names the cheaper rotation's cost, checked here on the
    rebuilt subproblem; the solver's pose is kept."""
    from solvers.certify.front import _dual_candidate, _normalised, tim_problem

    beta = 0.05
    gnc = register(corr.source, corr.target, noise_bound=beta)
    res = register(corr.source, corr.target, noise_bound=beta, certify=True, time_limit=3.0,
                   prefer="cost")
    rc = res.info["rotation_certificate"]
    assert rc["backend_status"] == "not attempted" and rc["status"] == "gap_too_large"
    assert not rc["certified"] and rc["lower_bound"] == 0.0
    assert "dual search not attempted" in rc["message"] and "not attempted" in res.message
    assert res.certificate.problem == "full_weighted_tls"
    assert res.cost == pytest.approx(gnc.cost, rel=1e-12)
    p = WeightedTLSProblem(corr.source, corr.target, noise_bound=beta)
    sub = tim_problem(p, np.asarray(rc["pairs"]))
    assert sub.cost(res.rotation) == pytest.approx(rc["upper_bound"], rel=1e-9)
    assert rc["better_upper_bound"] < rc["upper_bound"]
    cheaper = _dual_candidate(_normalised(sub)[0], res.rotation)
    assert sub.cost(cheaper) == pytest.approx(rc["better_upper_bound"], rel=1e-9)
    # prefer="certificate" still searches it (and certifies the subproblem: the slow tests).
    dflt = register(corr.source, corr.target, noise_bound=beta, certify=True, time_limit=0.5)
    rot = dflt.info.get("rotation_certificate") or dflt.certificate.to_dict()
    assert rot["backend_status"] != "not attempted"


def test_refine_translation_keeps_the_rotation_and_never_raises_the_cost() -> None:
    rng = np.random.default_rng(0)
    a = rng.uniform(-1, 1, (60, 3))
    R = Rotation.random(random_state=rng).as_matrix()
    b = a @ R.T + np.array([0.3, -0.2, 0.5]) + 0.01 * rng.normal(size=(60, 3))
    b[40:] = rng.uniform(-2, 2, (20, 3))
    p = WeightedTLSProblem(a, b, noise_bound=0.0554)
    t0 = np.array([0.31, -0.18, 0.48])
    t = refine_translation(p, R, t0)
    assert p.cost(R, t) <= p.cost(R, t0)
    # At the refined translation the inliers' weighted mean is the translation itself.
    S = p.inliers(R, t)
    assert np.allclose(t, (b[S] - a[S] @ R.T).mean(axis=0), atol=1e-12)


@pytest.mark.slow
def test_full_bound_searches_from_the_cheaper_solver_pose(corr, monkeypatch) -> None:
    """At 0.05 m the returned (rotation-certified) pose costs more than the solver's; the full
    problem's pose search starts from the solver's pose (its cost is the search's first upper
    bound), and its bound, below both costs, is recorded for the returned pose."""
    from solvers.certify import front

    starts = []
    real = front._pose_search_bound

    def spy(pn, R, t, **kw):  # noqa: ANN001, ANN003, ANN202
        starts.append(pn.cost(R, t))
        return real(pn, R, t, **kw)

    monkeypatch.setattr(front, "_pose_search_bound", spy)
    gnc = register(corr.source, corr.target, noise_bound=0.05)
    res = register(corr.source, corr.target, noise_bound=0.05, certify=True, time_limit=10.0)
    assert len(starts) == 1
    assert res.info["candidate_cost"] == pytest.approx(gnc.cost, rel=1e-12)
    if res.certificate.problem == "full_weighted_tls":  # the search certified in time
        full = res.certificate.to_dict()
        assert res.cost <= gnc.cost < res.info["subproblem_cost"]
    else:
        full = res.info["full_problem_certificate"]
        assert res.cost > res.info["candidate_cost"]
        assert full["upper_bound"] == pytest.approx(res.cost, rel=1e-9)
    ws = full["weight_scale"]
    assert starts[0] * ws == pytest.approx(res.info["candidate_cost"], rel=1e-9)
    assert full["lower_bound"] <= min(res.cost, res.info["candidate_cost"])
