"""The DE and MCMC baselines on a target with a known answer, at a fixed seed."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose.sampling.baselines import DEParams, MCMCParams, de_sample, mcmc_sample
from tests.test_sampling_sampler import _target_gaussian

R0 = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
t0 = np.array([0.1, 0.0, 0.6])
SIG = np.array([0.02, 0.02, 0.3, 0.003, 0.003, 0.003])
T0 = np.eye(4)
T0[:3, :3], T0[:3, 3] = R0, t0


def _chart_stats(d):
    x = d.tangent(R0, t0)
    m = d.weights @ x
    return m, np.sqrt(d.weights @ (x - m) ** 2)


@pytest.mark.slow
def test_mcmc_recovers_a_known_gaussian():
    start = T0.copy()
    start[:3, 3] += 0.005  # off the mode: warm-up has to find it
    res = mcmc_sample(_target_gaussian(R0, t0, SIG), start,
                      params=MCMCParams(max_evaluations=20_000, chains=16), rng=0)
    assert res.success, res.message
    assert res.method == "mcmc" and res.num_evaluations <= 20_000
    assert 0.1 < res.info["acceptance"] < 0.5
    assert res.ess > 100 and res.info["rhat"] < 1.1
    m, sd = _chart_stats(res.weighted)
    np.testing.assert_allclose(sd / SIG, 1.0, atol=0.2)
    assert np.all(np.abs(m / SIG) < 0.3)


@pytest.mark.slow
def test_de_population_is_a_valid_weighted_distribution():
    res = de_sample(_target_gaussian(R0, t0, SIG), T0,
                    params=DEParams(max_evaluations=1500, batch=50, resample=500), rng=0)
    d = res.weighted
    assert res.method == "de" and res.num_evaluations == 1500 and len(d) == 1500
    assert np.isclose(d.weights.sum(), 1.0) and np.all(d.weights > 0)
    assert d.log_weights is not None and np.isfinite(d.pareto_k())
    assert len(res.distribution) == 500
    # DE converges on the mode: its weighted population sits there, and (the documented bias)
    # is narrower than the target in every coordinate.
    m, sd = _chart_stats(d)
    assert np.all(np.abs(m / SIG) < 1.0)
    assert np.all(sd < SIG)
    # The same seed gives the same run.
    again = de_sample(_target_gaussian(R0, t0, SIG), T0,
                      params=DEParams(max_evaluations=1500, batch=50, resample=500), rng=0)
    np.testing.assert_array_equal(again.weighted.translations, d.translations)


def test_de_uses_suggested_initial_population():
    init = np.random.default_rng(0).normal(size=(40, 6)) * SIG * 0.1
    seen = []

    def target(T):
        seen.append(T.copy())
        return _target_gaussian(R0, t0, SIG)(T)

    de_sample(target, T0, params=DEParams(max_evaluations=40, batch=40), init=init, rng=0)
    x = np.concatenate(seen)
    got = np.hstack([Rotation.from_matrix(np.einsum("ji,njk->nik", R0, x[:, :3, :3])).as_rotvec(),
                     x[:, :3, 3] - t0])
    np.testing.assert_allclose(np.sort(got, axis=0), np.sort(init, axis=0), atol=1e-9)


def test_wall_clock_budget_stops_the_run():
    res = mcmc_sample(_target_gaussian(R0, t0, SIG), T0,
                      params=MCMCParams(max_evaluations=10**9, max_seconds=0.3, chains=8), rng=0)
    assert res.seconds < 2.0 and res.num_evaluations < 10**9


@pytest.mark.parametrize("kw", [dict(max_evaluations=0), dict(max_seconds=-1.0), dict(chains=1),
                                dict(warmup=1.0), dict(temperature=float("nan"))])
def test_bad_mcmc_params(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        MCMCParams(**kw)


@pytest.mark.parametrize("kw", [dict(batch=0), dict(rotation_bound=0.0), dict(resample=-1)])
def test_bad_de_params(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        DEParams(**kw)


def test_bad_inputs():
    f = _target_gaussian(R0, t0, SIG)
    with pytest.raises(ValueError, match="not a rotation"):
        de_sample(f, np.diag([1.0, 1.0, -1.0, 1.0]), params=DEParams(max_evaluations=10))
    with pytest.raises(ValueError, match=r"`init` to have shape \(m, 6\)"):
        de_sample(f, T0, params=DEParams(max_evaluations=10), init=np.zeros((3, 5)))
    with pytest.raises(ValueError, match="seeds"):
        mcmc_sample(f, np.full((4, 4), np.nan), params=MCMCParams(max_evaluations=10))
    with pytest.raises(ValueError, match="NaN"):
        mcmc_sample(lambda T: np.full(len(T), np.nan), T0, params=MCMCParams(max_evaluations=100))
    with pytest.raises(ValueError, match="zero target density"):
        mcmc_sample(lambda T: np.full(len(T), -np.inf), T0, params=MCMCParams(max_evaluations=100))
