"""Initial values from a pose or a PoseDistribution, accepted by the real Nevergrad, emcee, PyMC
and gtsam."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose.sampling import PoseDistribution
from certpose.sampling.chart import from_chart, to_chart
from certpose.sampling.initialisers import (
    emcee_walkers,
    gtsam_priors,
    initial_chart_points,
    initial_poses,
    nevergrad_parametrization,
    nevergrad_population,
    pymc_initvals,
    reference_pose,
)

R0 = Rotation.from_rotvec([0.2, -0.4, 0.9]).as_matrix()
T0 = np.eye(4)
T0[:3, :3], T0[:3, 3] = R0, [0.05, -0.02, 0.7]
SIG = np.array([0.01, 0.02, 0.3, 0.002, 0.001, 0.004])


def _dist(n: int = 3000, rng: int = 0) -> PoseDistribution:
    x = np.random.default_rng(rng).normal(size=(n, 6)) * SIG
    T = from_chart(x, T0)
    return PoseDistribution(T[:, :3, :3], T[:, :3, 3], np.full(n, 1.0 / n))


def test_chart_round_trip_and_validation():
    x = np.random.default_rng(1).normal(size=(50, 6)) * SIG
    T = from_chart(x, T0)
    np.testing.assert_allclose(to_chart(T[:, :3, :3], T[:, :3, 3], T0), x, atol=1e-12)
    with pytest.raises(ValueError, match=r"shape \(n, 6\)"):
        from_chart(np.zeros((3, 5)), T0)
    with pytest.raises(ValueError, match="NaN"):
        from_chart(np.full(6, np.nan), T0)
    bad = T0.copy()
    bad[:3, :3] *= 2
    with pytest.raises(ValueError, match="not a rotation"):
        from_chart(np.zeros(6), bad)


def test_points_follow_the_distribution_and_are_distinct():
    d = _dist()
    x = initial_chart_points(d, 4000, T_ref=T0, rng=0)
    assert len(np.unique(x, axis=0)) == 4000
    # Resampled particles plus a small kernel jitter: the spread is the distribution's.
    np.testing.assert_allclose(x.std(axis=0) / SIG, 1.0, atol=0.1)
    np.testing.assert_allclose(reference_pose(d)[:3, 3], T0[:3, 3], atol=3e-4)
    # A single pose (or an object with T_camera_object) gives an isotropic cloud around it.
    p = initial_poses(T0, 200, rng=1, rotation_sigma=0.01, translation_sigma=0.001)
    y = to_chart(p[:, :3, :3], p[:, :3, 3], T0)
    assert np.all(np.abs(y[:, :3]) < 0.06) and np.all(np.abs(y[:, 3:]) < 0.006)
    assert y[:, 3:].std() > 5e-4


@pytest.mark.parametrize("source, match", [
    (np.eye(3), r"shape \(4, 4\)"),
    (np.full((4, 4), np.nan), "NaN"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "not a rotation"),
])
def test_bad_sources(source, match):
    with pytest.raises(ValueError, match=match):
        initial_chart_points(source, 5)


def test_bad_counts():
    with pytest.raises(ValueError, match="nwalkers"):
        emcee_walkers(T0, 6)
    with pytest.raises(ValueError, match="`n` >= 1"):
        initial_chart_points(T0, 0)
    with pytest.raises(ValueError, match="rotation_sigma"):
        initial_chart_points(T0, 3, rotation_sigma=-1.0)


def test_nevergrad_accepts_parametrization_and_population():
    import nevergrad as ng

    d = _dist()
    param = nevergrad_parametrization(d, T_ref=T0)
    np.testing.assert_allclose(param.value, np.zeros(6), atol=0.02)
    pop = nevergrad_population(d, 20, T_ref=T0, rng=0)
    opt = ng.optimizers.TwoPointsDE(parametrization=param, budget=60, num_workers=20)
    for x in pop:
        opt.suggest(x)
    asked = [opt.ask() for _ in range(20)]
    # Nevergrad hands suggestions back last in, first out.
    np.testing.assert_allclose(np.stack([a.value for a in asked])[::-1], pop, atol=1e-9)
    for a in asked:
        opt.tell(a, float(np.sum((np.asarray(a.value) / SIG) ** 2)))
    rec = opt.provide_recommendation().value
    assert np.all(np.abs(rec / SIG) < 6)


def test_emcee_walkers_pass_emcee_checks_and_sample():
    import emcee

    walkers = emcee_walkers(_dist(), 24, T_ref=T0, rng=0)

    def log_prob(x):
        return -0.5 * np.sum((x / SIG) ** 2)

    sampler = emcee.EnsembleSampler(24, 6, log_prob)
    sampler.random_state = np.random.RandomState(1).get_state()
    state = sampler.run_mcmc(walkers, 50)  # emcee's own initial-state check runs here
    assert np.all(np.isfinite(state.log_prob))
    assert sampler.get_chain().shape == (50, 24, 6)
    # Identical walkers (a collapsed source) are what emcee refuses; ours never are.
    with pytest.raises(ValueError):
        emcee.EnsembleSampler(24, 6, log_prob).run_mcmc(np.tile(walkers[0], (24, 1)), 2)


@pytest.mark.slow
def test_pymc_accepts_initvals():
    import pymc as pm

    iv = pymc_initvals(_dist(), 2, T_ref=T0, rng=0)
    with pm.Model():
        pm.Normal("xi", mu=0.0, sigma=SIG, shape=6)
        idata = pm.sample(draws=20, tune=20, chains=2, cores=1, initvals=iv, random_seed=0,
                          progressbar=False, compute_convergence_checks=False)
    xi = idata.posterior["xi"].values
    assert xi.shape == (2, 20, 6) and np.all(np.isfinite(xi))


def test_gtsam_prior_factor_per_mode_in_a_graph():
    import gtsam

    # Two modes: the heavy one around T0, a light one 180 deg about the object z axis.
    d1 = _dist(2000)
    flip = T0 @ np.diag([-1.0, -1.0, 1.0, 1.0])
    x = np.random.default_rng(5).normal(size=(500, 6)) * SIG * 0.5
    T2 = from_chart(x, flip)
    d = PoseDistribution(np.concatenate([d1.rotations, T2[:, :3, :3]]),
                         np.concatenate([d1.translations, T2[:, :3, 3]]),
                         np.r_[np.full(2000, 0.8 / 2000), np.full(500, 0.2 / 500)])
    key = gtsam.symbol("x", 0)
    priors = gtsam_priors(d, key)
    assert [round(m, 3) for _, m in priors] == [0.8, 0.2]
    factor, _ = priors[0]
    graph = gtsam.NonlinearFactorGraph()
    graph.add(factor)
    init = gtsam.Values()
    init.insert(key, gtsam.Pose3(gtsam.Rot3(R0 @ Rotation.from_rotvec([0.05, 0, 0.2]).as_matrix()),
                                 gtsam.Point3(*(T0[:3, 3] + 0.01))))
    res = gtsam.LevenbergMarquardtOptimizer(graph, init).optimize()
    mode = d.modes()[0]
    np.testing.assert_allclose(res.atPose3(key).matrix(), mode.T, atol=1e-6)
    # The prior's covariance is the mode's, in gtsam's body-frame tangent ordering.
    cov = gtsam.Marginals(graph, res).marginalCovariance(key)
    J = np.zeros((6, 6))
    J[:3, :3], J[3:, 3:] = np.eye(3), mode.rotation.T
    np.testing.assert_allclose(cov, J @ mode.covariance @ J.T, rtol=1e-3, atol=1e-10)
    # Body-frame check, independent of the formula: a particle's gtsam local coordinates
    # have the mode's spread.
    prior_pose = factor.prior()
    loc = np.stack([prior_pose.localCoordinates(gtsam.Pose3(T)) for T in d1.poses[:2000]])
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), loc.std(axis=0), rtol=0.1)
    # A single pose also gives one prior factor.
    (f1, m1), = gtsam_priors(T0, key, rotation_sigma=0.01, translation_sigma=0.001)
    assert m1 == 1.0 and np.allclose(f1.prior().matrix(), T0)
