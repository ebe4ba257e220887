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
    fit_calibration,
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

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "benchmarks"))
    from bench_sampler import build_demo

    from certpose.sampling.sampler import seeds_from_mle

    # The voxel-averaged model (no axial resampling): its eq. (1) has basins along the hidden
    # handle's arc; with the flat arc of the demo's default model the truth is at some angle
    # of a ridge that no set of basins covers (0.95 credible level, measured 2026-11-26).
    lik, mle, gt = build_demo(seed=0, revolution=None)
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


def _cases_with_known_error(n, sr, st, rng):
    """``n`` one-basin cases whose truths are their basins moved by a Gaussian model error of
    ``sr`` rad and ``st`` m per axis (a tight Laplace covariance: the error dominates)."""
    cases = []
    C = np.diag([np.radians(0.2) ** 2] * 3 + [1e-4**2] * 3)
    for _ in range(n):
        B = _pose(np.hstack([rng.normal(0, 1, 3), rng.normal(0, 0.2, 3)]))
        e = _pose(np.hstack([rng.normal(0, sr, 3), np.zeros(3)]))
        T = B @ e
        T[:3, 3] += rng.normal(0, st, 3)
        cases.append((Basins(B[None], np.zeros(1), C[None], 10.0), T))
    return cases


def test_fit_calibration_recovers_a_known_model_error():
    sr, st = math.radians(3.0), 0.002
    cases = _cases_with_known_error(120, sr, st, np.random.default_rng(3))
    fit = fit_calibration(cases, basin_temperatures=(math.inf,), dofs=(math.inf,), draws=400)
    # Median-based scale estimates of 120 chi2_3 draws: about 5% standard error.
    assert fit.params.rotation_sigma == pytest.approx(sr, rel=0.15)
    assert fit.params.translation_sigma == pytest.approx(st, rel=0.15)
    assert fit.num_right == 120 and len(fit.table) == 1
    # The fitted distribution is calibrated on its own training cases.
    _, _, in90, in50 = fit.table[0]
    assert abs(in90 - 0.9) < 0.1 and abs(in50 - 0.5) < 0.12
    # A symmetric object's equivalents: the best one counts, a far decoy changes nothing.
    far = _pose(np.array([0, 0, 0, 1.0, 0, 0]))
    decoyed = [(b, np.stack([T, far])) for b, T in cases[:20]]
    assert fit_calibration(decoyed, basin_temperatures=(math.inf,), dofs=(math.inf,), draws=400).params \
        == fit_calibration(cases[:20], basin_temperatures=(math.inf,), dofs=(math.inf,), draws=400).params


def test_fit_calibration_prefers_the_sharpest_tied_basin_temperature():
    rng = np.random.default_rng(4)
    cases = _cases_with_known_error(30, math.radians(3.0), 0.002, rng)
    # A half-turned, much worse extra basin per case: basin temperatures up to 1e3 give it no mass
    # (1e4 nats down) and "inf" half the mass, which moves no level (the two components are
    # congruent): every fit ties, and the sharpest (lowest) temperature wins, whatever the order.
    flip = _pose(np.array([math.pi, 0, 0, 0, 0, 0]))
    two = [(Basins(np.stack([b.poses[0], b.poses[0] @ flip]), np.array([0.0, -1e4]),
                   np.repeat(b.laplace_covariances, 2, axis=0), 10.0), T) for b, T in cases]
    fit = fit_calibration(two, basin_temperatures=(1e3, math.inf, 100.0), dofs=(math.inf,), draws=400)
    assert fit.params.basin_temperature == 100.0
    assert [r[1] for r in fit.table] == [1e3, math.inf, 100.0]


def test_fit_calibration_bad_inputs():
    with pytest.raises(ValueError, match="cases"):
        fit_calibration([])
    far = [(b, _pose(np.array([0, 0, 2.0, 0, 0, 0]))) for b, _ in
           _cases_with_known_error(3, 0.05, 0.002, np.random.default_rng(0))]
    with pytest.raises(ValueError, match="right_basin_deg"):
        fit_calibration(far, right_basin_deg=30.0)
