"""Credible levels (the sampler's, ranked by its target; the calibrated mixture's) against known
answers, the calibrated distribution's construction, and its bad inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from certpose.sampling.calibration import (
    Basins,
    CalibrationParams,
    calibrated_distribution,
    find_basins,
)
from certpose.sampling.sampler import ISParams, importance_sample

SD = np.array([0.05, 0.08, 0.03, 0.002, 0.004, 0.003])


def _pose(x: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
    T[:3, 3] = x[3:]
    return T


def _gauss(T: np.ndarray) -> np.ndarray:
    # log N in the chart at the identity, times the inverse Jacobian of the exp map: exactly a
    # Gaussian in the chart, so the highest-density region is a chi2_6 ellipsoid up to the
    # Jacobian (a relative change of theta^2/12 ~ 1e-3 over this spread).
    x = np.hstack([Rotation.from_matrix(T[:, :3, :3]).as_rotvec(), T[:, :3, 3]])
    return -0.5 * np.sum((x / SD) ** 2, axis=1)


@pytest.mark.parametrize("level", [0.2, 0.5, 0.9])
def test_sampler_level_of_a_known_gaussian(level):
    res = importance_sample(_gauss, np.eye(4), params=ISParams(draws=8000, temperature=2.0), rng=1)
    # A pose at Mahalanobis^2 r under the tempered target (covariance 2 SD^2): level chi2_6.cdf(r).
    r = chi2.ppf(level, 6)
    x = np.sqrt(2.0 * r) * SD * np.array([1, 0, 0, 0, 0, 0])
    got = res.credible_level(_gauss(_pose(x)[None])[0])
    assert abs(got - level) < 0.04
    assert res.log_target.shape == (len(res.weighted),)
    assert res.credible_level(-np.inf) == 1.0
    with pytest.raises(ValueError, match="nan"):
        res.credible_level(float("nan"))


def _basins(values, offsets=((0, 0, 0, 0, 0, 0),)) -> Basins:
    P = np.stack([_pose(np.asarray(o, dtype=float)) for o in offsets])
    C = np.repeat(np.diag(SD**2)[None], len(P), axis=0)
    return Basins(P, np.asarray(values, dtype=float), C, 10.0)


@pytest.mark.parametrize("level", [0.3, 0.9])
def test_calibrated_level_of_one_basin(level):
    p = CalibrationParams(rotation_sigma=0.04, translation_sigma=0.003, dof=math.inf)
    d = calibrated_distribution(None, basins=_basins([0.0]), params=p)
    sd = np.sqrt(SD**2 + np.array([0.04**2] * 3 + [0.003**2] * 3))
    x = np.sqrt(chi2.ppf(level, 6)) * sd * np.array([0, 0, 0, 0, 1, 0])
    assert abs(d.credible_level(_pose(x), draws=20000) - level) < 0.02
    # The best of several poses counts (a symmetric object's equivalents).
    far = _pose(np.array([0, 0, 0, 0.1, 0, 0]))
    assert d.credible_level(np.stack([far, _pose(x)]), draws=20000) == pytest.approx(
        d.credible_level(_pose(x), draws=20000))
    draws = d.sample(500, rng=0)
    assert len(draws) == 500 and np.allclose(draws.weights.sum(), 1.0)


def test_basin_weights_follow_the_basin_temperature():
    flip = (math.pi, 0, 0, 0, 0, 0)
    b = _basins([0.0, -100.0, -5000.0], [(0, 0, 0, 0, 0, 0), flip, (0, 0, 0, 0.05, 0, 0)])
    d = calibrated_distribution(None, basins=b, params=CalibrationParams(basin_temperature=100.0,
                                                                        dof=math.inf))
    # The third basin is e^-50 down: dropped; the first two in the ratio 1 : e^-1.
    assert len(d.mixture.weights) == 2
    assert d.mixture.weights[1] / d.mixture.weights[0] == pytest.approx(math.exp(-1.0))
    even = calibrated_distribution(None, basins=b, params=CalibrationParams(basin_temperature=math.inf))
    assert np.allclose(even.mixture.weights, 1 / 3)
    # Heavy tails: a Student t model error puts more mass far out than the Gaussian.
    far = _pose(np.array([0, 0, 0.5, 0, 0, 0]))
    t = calibrated_distribution(None, basins=b, params=CalibrationParams(basin_temperature=100.0, dof=3.0))
    assert t.mixture.dof == 3.0 and t.log_density(far)[0] > d.log_density(far)[0]


@pytest.mark.parametrize("kw, match", [
    (dict(rotation_sigma=0.0), "rotation_sigma"),
    (dict(translation_sigma=float("nan")), "translation_sigma"),
    (dict(basin_temperature=-1.0), "basin_temperature"),
    (dict(dof=2.0), "dof"),
])
def test_bad_params(kw, match):
    with pytest.raises(ValueError, match=match):
        CalibrationParams(**kw)


def test_bad_inputs():
    with pytest.raises(ValueError, match="seeds"):
        calibrated_distribution(None)
    with pytest.raises(ValueError, match="-inf"):
        calibrated_distribution(None, basins=_basins([-np.inf]))
    d = calibrated_distribution(None, basins=_basins([0.0]))
    with pytest.raises(ValueError, match="n"):
        d.sample(0)


@pytest.mark.slow
def test_find_basins_on_the_demo_finds_the_flips():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
    from bench_sampler import build_demo

    from certpose.sampling.sampler import seeds_from_mle

    lik, mle, gt = build_demo(seed=0)
    seeds = seeds_from_mle(mle)
    b = find_basins(lik, seeds)
    assert len(b.poses) >= 1 and b.poses.shape[1:] == (4, 4)
    # The MLE is a basin and no basin beats it by more than refinement noise.
    assert b.log_likelihood.max() <= lik(seeds[:1])[0] + 5.0
    assert np.allclose(b.poses[0], seeds[0]) or b.log_likelihood[0] >= lik(seeds[:1])[0]
    # Laplace covariances are positive definite; the truth is inside the 90% region.
    assert np.all(np.linalg.eigvalsh(b.laplace_covariances) > 0)
    d = calibrated_distribution(lik, basins=b)
    assert d.credible_level(gt) <= 0.9
    no_flips = find_basins(lik, seeds, flips=False)
    assert len(no_flips.poses) <= len(b.poses)
