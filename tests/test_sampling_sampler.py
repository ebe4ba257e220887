"""The noise-injected importance sampler: exact proposal density, a known-answer target, the demo."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.special import logsumexp
from scipy.stats import norm

from certpose.sampling.distribution import PoseDistribution
from certpose.sampling.sampler import ISParams, TangentMixture, importance_sample


def _mixture(dof: float = np.inf) -> TangentMixture:
    Rs = Rotation.from_rotvec([[0, 0, 0], [0, 0, 1.0]]).as_matrix()
    covs = np.stack([np.diag([0.5**2] * 3 + [0.01**2] * 3),
                     np.diag([0.2, 0.3, 0.1, 1e-4, 1e-4, 2e-4])])
    return TangentMixture(Rs, np.array([[0, 0, 0], [0.01, 0, 0]]), covs, np.array([0.6, 0.4]), dof)


@pytest.mark.slow
@pytest.mark.parametrize("dof", [np.inf, 5.0])
def test_proposal_density_integrates_to_one_and_matches_frequencies(dof):
    # Monte Carlo with Haar-uniform rotations (volume 8 pi^2 in the chart's normalisation) and
    # Gaussian translations: independent of the density's own sampler and formula. With 5 dof
    # the t's wrap terms beyond |m| = 1 are not negligible for the 0.5 rad component, so that
    # component is narrowed to keep the check about the density, not the truncation.
    mix = _mixture(dof)
    if np.isfinite(dof):
        covs = mix.covariances.copy()
        covs[0, :3, :3] = np.eye(3) * 0.2**2
        mix = TangentMixture(mix.rotations, mix.translations, covs, mix.weights, dof)
    rng = np.random.default_rng(0)
    n, s = 400_000, 0.015
    R = Rotation.random(n, random_state=1).as_matrix()
    t = rng.normal(0.0, s, (n, 3)) + [0.005, 0, 0]
    ref = norm.logpdf(t, loc=[0.005, 0, 0], scale=s).sum(axis=1)
    v = np.exp(mix.log_density(R, t) - ref) * 8 * np.pi**2
    err = v.std() / np.sqrt(n)
    assert abs(v.mean() - 1.0) < 4 * err + 0.01
    # Probability of a region: frequency of the mixture's draws against the density's integral.
    Rd, td = mix.sample(200_000, rng)
    angle = np.linalg.norm(Rotation.from_matrix(Rd).as_rotvec(), axis=1)
    freq = np.mean((angle < 0.6) & (td[:, 0] < 0.005))
    angle_u = np.linalg.norm(Rotation.from_matrix(R).as_rotvec(), axis=1)
    inside = (angle_u < 0.6) & (t[:, 0] < 0.005)
    est = np.mean(v * inside)
    assert abs(freq - est) < 4 * (v * inside).std() / np.sqrt(n) + 0.005


@pytest.mark.parametrize("dof", [np.inf, 5.0])
def test_compiled_proposal_density_is_the_numpy_one(dof, monkeypatch):
    # certpose.sampling._kernels repeats the NumPy path's arithmetic draw by draw: the same
    # values, near the identity and near half turns (Shepperd's branch) included.
    import certpose.sampling.sampler as S

    rng = np.random.default_rng(0)
    mix = _mixture(dof)
    R, t = mix.sample(3000, rng)
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    angles = np.concatenate([np.pi - rng.uniform(0.0, 0.15, 20), rng.uniform(0.0, 1e-6, 20)])
    R[:40] = mix.rotations[0] @ Rotation.from_rotvec(axes * angles[:, None]).as_matrix()
    R[40:45] = mix.rotations[1]
    monkeypatch.setattr(S, "_COMPILED_DENSITY", False)
    ref = mix.component_log_densities(R, t)
    monkeypatch.setattr(S, "_COMPILED_DENSITY", True)
    got = mix.component_log_densities(R, t)
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(mix.log_density(R[:5], t[:5]), logsumexp(ref[:, :5], axis=0), rtol=1e-10)


def test_proposal_density_student_t_near_identity():
    from scipy.stats import multivariate_t

    C = np.diag([0.1**2] * 3 + [0.01**2] * 3)
    mix = TangentMixture(np.eye(3)[None], np.zeros((1, 3)), C[None], np.ones(1), 5.0)
    # (Not at the identity itself: there the t's tail on the |w| = 2 pi shell, which the exp map
    # folds onto that one point, is a real, integrable spike of the density.)
    x = np.array([[1e-4, 0, 0, 0.001, 0, 0], [0.01, 0.02, 0, 0, -0.004, 0.002]])
    lq = mix.log_density(Rotation.from_rotvec(x[:, :3]).as_matrix(), x[:, 3:])
    theta = np.linalg.norm(x[:, :3], axis=1)
    jac = np.log(4 * np.sin(theta / 2) ** 2 / theta**2)
    np.testing.assert_allclose(lq, multivariate_t(np.zeros(6), C, df=5.0).logpdf(x) - jac, atol=1e-6)
    with pytest.raises(ValueError, match="dof"):
        TangentMixture(np.eye(3)[None], np.zeros((1, 3)), C[None], np.ones(1), 2.0)


def test_proposal_density_near_identity_is_the_gaussian():
    mix = TangentMixture(np.eye(3)[None], np.zeros((1, 3)), np.diag([0.1**2] * 3 + [0.01**2] * 3)[None],
                         np.ones(1))
    w = np.array([[1e-9, 0, 0], [0.01, 0, 0]])
    lq = mix.log_density(Rotation.from_rotvec(w).as_matrix(), np.zeros((2, 3)))
    theta = np.linalg.norm(w, axis=1)
    gauss = norm.logpdf(w, scale=0.1).sum(1) + 3 * norm.logpdf(0, scale=0.01)
    jac = np.log(4 * np.sin(theta / 2) ** 2 / theta**2)
    np.testing.assert_allclose(lq, gauss - jac, atol=1e-6)


def _target_gaussian(R0: np.ndarray, t0: np.ndarray, sig: np.ndarray):
    # A target with a known exact density: the push-forward of a tangent Gaussian around (R0, t0),
    # written here independently of TangentMixture (no wrap terms: mass beyond pi is < 1e-6).
    def log_target(T: np.ndarray) -> np.ndarray:
        w = Rotation.from_matrix(np.einsum("ji,njk->nik", R0, T[:, :3, :3])).as_rotvec()
        x = np.concatenate([w, T[:, :3, 3] - t0], axis=1)
        theta = np.linalg.norm(w, axis=1)
        jac = np.log(np.where(theta > 1e-8, 2 * (1 - np.cos(theta)) / np.maximum(theta, 1e-8) ** 2, 1.0))
        return norm.logpdf(x, scale=sig).sum(axis=1) - jac
    return log_target


def test_known_answer_marginal_and_ess():
    R0 = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    t0 = np.array([0.1, 0.0, 0.6])
    sig = np.array([0.02, 0.02, 0.6, 0.003, 0.003, 0.003])  # a wide arc about the object z axis
    seeds = np.tile(np.eye(4), (2, 1, 1))
    for k, a in enumerate([0.4, -0.3]):
        seeds[k, :3, :3] = R0 @ Rotation.from_rotvec([0.01, 0, a]).as_matrix()
        seeds[k, :3, 3] = t0 + [0.004, 0, 0]
    res = importance_sample(_target_gaussian(R0, t0, sig), seeds,
                            params=ISParams(draws=8000, temperature=1.0), rng=3)
    assert res.success, res.message
    d = res.weighted
    assert d.ess > 1000
    assert d.pareto_k() < 0.7
    wz = d.tangent(R0, t0)[:, 2]
    # Weighted empirical CDF of the angle about z against the exact N(0, 0.6^2) marginal.
    order = np.argsort(wz)
    cdf = np.cumsum(d.weights[order])
    ks = np.max(np.abs(cdf - norm.cdf(wz[order], scale=0.6)))
    assert ks < 0.05, ks
    # Total variation of a 20-bin histogram of the marginal.
    edges = np.linspace(-1.8, 1.8, 21)
    h, _ = np.histogram(wz, edges, weights=d.weights)
    exact = np.diff(norm.cdf(edges, scale=0.6))
    assert 0.5 * np.abs(h - exact).sum() < 0.1
    # Same seed, same answer.
    res2 = importance_sample(_target_gaussian(R0, t0, sig), seeds,
                             params=ISParams(draws=8000, temperature=1.0), rng=3)
    np.testing.assert_array_equal(res2.weighted.weights, d.weights)


def _banana(R0: np.ndarray, t0: np.ndarray, half: float, soft: float, radius: float,
            sig_w: float, sig_t: float):
    """An arc-shaped target with a known marginal: in the chart around (R0, t0) the spin ``phi``
    about the object z axis follows a uniform on [-half, half] smoothed by N(0, soft^2); the
    tilt is N(0, sig_w^2) per axis; the translation follows the arc,
    ``t0 + radius (cos phi - 1, sin phi, 0)`` plus N(0, sig_t^2) per axis (a banana in
    SO(3) x R^3: rotating about an axis off the object's origin). Returns the log-density (per
    Haar x Lebesgue) and the exact CDF of ``phi``."""
    def log_target(T: np.ndarray) -> np.ndarray:
        w = Rotation.from_matrix(np.einsum("ji,njk->nik", R0, T[:, :3, :3])).as_rotvec()
        phi = w[:, 2]
        g = norm.cdf((phi + half) / soft) - norm.cdf((phi - half) / soft)
        c = radius * np.stack([np.cos(phi) - 1, np.sin(phi), np.zeros_like(phi)], axis=1)
        theta = np.linalg.norm(w, axis=1)
        jac = np.log(np.where(theta > 1e-8, 2 * (1 - np.cos(theta)) / np.maximum(theta, 1e-8) ** 2, 1.0))
        return (norm.logpdf(w[:, :2], scale=sig_w).sum(1) + np.log(g + 1e-300)
                + norm.logpdf(T[:, :3, 3] - t0 - c, scale=sig_t).sum(1) - jac)

    def cdf(phi: np.ndarray) -> np.ndarray:
        f = lambda z: z * norm.cdf(z) + norm.pdf(z)  # noqa: E731 - antiderivative of norm.cdf
        return soft * (f((phi + half) / soft) - f((phi - half) / soft)) / (2 * half)

    return log_target, cdf


def test_arc_shaped_target_high_ess_and_exact_marginal():
    # A hidden-handle-like arc: 1.6 rad of free spin, the translation swinging 2 cm along it,
    # seeds on a small part of it (as the MLE's are); tilt 1 deg, translation 2 mm. The
    # sampler before the Laplace start and bounded refits reached ESS 894 of 4,000 here.
    R0 = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    t0 = np.array([0.1, 0.0, 0.6])
    radius, sig_t = 0.03, 0.002
    log_target, cdf = _banana(R0, t0, 0.8, 0.1, radius, 0.02, sig_t)
    seeds = np.tile(np.eye(4), (2, 1, 1))
    for k, a in enumerate([0.0, 0.25]):
        seeds[k, :3, :3] = R0 @ Rotation.from_rotvec([0.01, 0, a]).as_matrix()
        seeds[k, :3, 3] = t0 + radius * np.array([np.cos(a) - 1, np.sin(a), 0]) + [0.001, 0, 0]
    res = importance_sample(log_target, seeds, params=ISParams(draws=4000, temperature=1.0), rng=0)
    assert res.success, res.message
    d = res.weighted
    assert d.ess > 1200, res.ess_per_round  # 30% of the final draws
    assert d.pareto_k() < 0.7
    x = d.tangent(R0, t0)
    phi = x[:, 2]
    order = np.argsort(phi)
    ks = np.max(np.abs(np.cumsum(d.weights[order]) - cdf(phi[order])))
    assert ks < 0.04, ks
    edges = np.linspace(-1.2, 1.2, 25)
    h, _ = np.histogram(phi, edges, weights=d.weights)
    assert 0.5 * np.abs(h - np.diff(cdf(edges))).sum() < 0.08
    # The banana: translations follow the arc with the right spread about it.
    resid = x[:, 3:] - radius * np.stack([np.cos(phi) - 1, np.sin(phi), np.zeros_like(phi)], axis=1)
    sd = np.sqrt(d.weights @ (resid - d.weights @ resid) ** 2)
    np.testing.assert_allclose(sd, sig_t, rtol=0.15)


def _two_runs(R0: np.ndarray, t0: np.ndarray, centre: np.ndarray, runs, soft: float,
              sig_w: float, sig_t: float):
    """A hidden handle with two free runs (scene 0000's mug: the arc, and the handle behind the
    foam brick): in the chart around (R0, t0) the spin ``phi`` about the object z axis has
    density ``sum_runs [Phi((phi - a) / soft) - Phi((phi - b) / soft)]`` (equal heights), the
    tilt is N(0, sig_w^2) per axis, and the pose turns rigidly about the axis through the object
    point ``centre``: ``t = t0 + R0 (centre - Rz(phi) centre)`` plus N(0, sig_t^2) per axis. The
    density is a product in chart coordinates, so the marginal of ``phi`` is exactly the
    normalised sum. Returns the log-density (per Haar x Lebesgue) and the exact CDF of ``phi``."""
    def g(phi: np.ndarray) -> np.ndarray:
        return sum(norm.cdf((phi - a) / soft) - norm.cdf((phi - b) / soft) for a, b in runs)

    def log_target(T: np.ndarray) -> np.ndarray:
        w = Rotation.from_matrix(np.einsum("ji,njk->nik", R0, T[:, :3, :3])).as_rotvec()
        phi = w[:, 2]
        Rz = Rotation.from_rotvec(phi[:, None] * [0.0, 0.0, 1.0]).as_matrix()
        c = (centre - Rz @ centre) @ R0.T
        theta = np.linalg.norm(w, axis=1)
        jac = np.log(np.where(theta > 1e-8, 2 * (1 - np.cos(theta)) / np.maximum(theta, 1e-8) ** 2, 1.0))
        return (norm.logpdf(w[:, :2], scale=sig_w).sum(1) + np.log(g(phi) + 1e-300)
                + norm.logpdf(T[:, :3, 3] - t0 - c, scale=sig_t).sum(1) - jac)

    def cdf(phi: np.ndarray) -> np.ndarray:
        f = lambda z: z * norm.cdf(z) + norm.pdf(z)  # noqa: E731 - antiderivative of norm.cdf
        total = sum(b - a for a, b in runs)
        return sum(soft * (f((phi - a) / soft) - f((phi - b) / soft)) for a, b in runs) / total

    return log_target, cdf


def test_second_free_run_found_from_seeds_in_the_first():
    # Seeds in one run only, as an MLE seeded in the arc leaves them; the other run (a third
    # of the arc's width, 80 deg away, a barrier of e^-60 between) holds 27% of the mass. The
    # sampler before the sweeps put none of its mass there (ESS 4,000 of 4,000, all of it in
    # the arc); a seed in the other run gave the opposite answer.
    R0 = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    t0 = np.array([0.1, 0.0, 0.6])
    runs = [(-0.8, 0.8), (2.2, 2.8)]
    log_target, cdf = _two_runs(R0, t0, np.array([0.004, 0.0, 0.0]), runs, 0.05, 0.02, 0.002)
    for a in (0.0, 2.5):
        seeds = np.tile(np.eye(4), (2, 1, 1))
        for k, da in enumerate([0.0, 0.2]):
            Rz = Rotation.from_rotvec([0.01, 0, a - 0.1 + da]).as_matrix()
            seeds[k, :3, :3] = R0 @ Rz
            seeds[k, :3, 3] = t0 + R0 @ ([0.004, 0, 0] - Rz @ [0.004, 0, 0]) + [0.001, 0, 0]
        res = importance_sample(log_target, seeds, params=ISParams(draws=4000, temperature=1.0), rng=0)
        assert res.success, res.message
        d = res.weighted
        assert d.ess > 1000, res.message
        phi = d.tangent(R0, t0)[:, 2]
        second = float(d.weights[phi > 1.5].sum())
        assert abs(second - 0.6 / 2.2) < 0.05, (a, second)
        edges = np.linspace(-1.2, 3.0, 29)
        h, _ = np.histogram(phi, edges, weights=d.weights)
        assert 0.5 * np.abs(h - np.diff(cdf(edges))).sum() < 0.1, (a, h)


def test_light_ring_of_its_own_is_swept():
    # Two rings 180 deg apart (the demo's mug upright and upside down, each free to spin over
    # its run): the light one holds 4% of the mass and has one seed with a fixed 5% share (as
    # the half turns of sample_pose_distribution get). Its component draws a few pilot draws per
    # round, never widens along its ring and is never among the heaviest swept: before
    # sweep_basins its draws missed most of the ring (rng 1: 0.4% of the mass instead of 4%;
    # rng 2: the ring's spin marginal 0.87 in total variation from the exact one, ESS 973).
    R0 = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    t0 = np.array([0.1, 0.0, 0.6])
    c = np.array([0.004, 0.0, 0.0])
    F = Rotation.from_rotvec([np.pi, 0.0, 0.0]).as_matrix()
    R1, t1 = R0 @ F, t0 + R0 @ (c - F @ c) + [0.0, 0.0, 0.002]
    mass = 0.04
    upright, _ = _two_runs(R0, t0, c, [(-0.8, 0.8)], 0.05, 0.02, 0.002)
    upside, cdf = _two_runs(R1, t1, c, [(-1.2, 1.2)], 0.05, 0.02, 0.002)
    # Each ring's density integrates to its run's width (1.6 and 2.4 rad).
    shift = np.log(mass / (1.0 - mass) * 1.6 / 2.4)

    def log_target(T: np.ndarray) -> np.ndarray:
        return np.logaddexp(upright(T), upside(T) + shift)

    def seed(R: np.ndarray, t: np.ndarray, a: float) -> np.ndarray:
        Rz = Rotation.from_rotvec([0.01, 0.0, a]).as_matrix()
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R @ Rz, t + R @ (c - Rz @ c) + [0.001, 0.0, 0.0]
        return T

    seeds = np.stack([seed(R0, t0, -0.1), seed(R0, t0, 0.1), seed(R1, t1, 0.3)])
    for rng in range(3):
        res = importance_sample(log_target, seeds, params=ISParams(temperature=1.0, sweep_basins=3), rng=rng,
                                fixed_share=[np.nan, np.nan, 0.05])
        d = res.weighted
        assert d.ess > 2000, res.message
        x = d.tangent(R1, t1)
        ring = np.linalg.norm(x[:, :2], axis=1) < 0.5
        assert abs(float(d.weights[ring].sum()) - mass) < 0.015, (rng, d.weights[ring].sum())
        edges = np.linspace(-1.6, 1.6, 17)
        h, _ = np.histogram(x[ring, 2], edges, weights=d.weights[ring])
        assert 0.5 * np.abs(h / h.sum() - np.diff(cdf(edges))).sum() < 0.3, (rng, h)


@pytest.mark.parametrize("seeds, match", [
    (np.zeros((0, 4, 4)), "shape"),
    (np.ones((3, 3)), "shape"),
    (np.full((4, 4), np.nan), "NaN"),
    (np.diag([2.0, 1, 1, 1]), "not a rotation"),
])
def test_bad_seeds(seeds, match):
    with pytest.raises(ValueError, match=match):
        importance_sample(lambda T: np.zeros(len(T)), seeds)


@pytest.mark.parametrize("kw", [{"draws": 1}, {"rounds": 0}, {"rotation_noise": -1.0},
                                {"temperature": 0.0}, {"defensive": 1.0}, {"translation_noise": np.nan},
                                {"max_growth": 1.0}, {"max_translation_noise": 0.0}, {"dof": 2.0},
                                {"weight_damping": 1.0}, {"min_component_weight": -0.1},
                                {"sweep_step": 0.0}, {"sweep_window": np.inf}, {"sweep_max_new": 0}, {"sweep_basins": 0},
                                {"sweep_rounds": (-1,)}, {"half_turn_window": 0.0},
                                {"half_turn_share": 0.0}, {"half_turn_share": 0.4}])
def test_bad_params(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        ISParams(**kw)


def test_bad_target_output():
    with pytest.raises(ValueError, match="shape"):
        importance_sample(lambda T: np.zeros(3), np.eye(4), params=ISParams(draws=10, rounds=1))
    with pytest.raises(ValueError, match="NaN"):
        importance_sample(lambda T: np.full(len(T), np.nan), np.eye(4), params=ISParams(draws=10, rounds=1))


@pytest.mark.slow
def test_demo_scene_real_likelihood_concentrates_on_truth():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "benchmarks"))
    from bench_sampler import build_demo

    from certpose.sampling.sampler import sample_pose_distribution, seeds_from_mle

    lik, mle, gt = build_demo(seed=0)
    seeds = seeds_from_mle(mle)
    res = sample_pose_distribution(lik, seeds, params=ISParams(draws=4000, resample=4000), rng=0)
    assert res.success, res.message
    assert res.temperature > 1.0
    assert res.weighted.ess > 100
    d = res.distribution
    assert len(d) == 4000
    x = d.tangent(gt[:3, :3], gt[:3, 3])
    # The mug's axis (object z) and position: 95% of the mass near the truth. The rotation
    # about the axis is free (the handle is hidden), so it is not checked.
    tilt = np.degrees(np.arccos(np.clip(d.rotations[:, :, 2] @ gt[:3, 2], -1, 1)))
    assert np.quantile(tilt, 0.95) < 8.0
    assert np.quantile(np.linalg.norm(x[:, 3:], axis=1), 0.95) < 0.01


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 9])
def test_demo_scene_keeps_its_ess(seed):
    # The demo at seeds 1 and 9 (MLE and sampler): the sampler before the sweeps ended at ESS
    # 238 and 903 of 10,000 (seed 1 with an earlier MLE: 2); with sweeps but no births, seed 9
    # at 931: tail draws on a peak no component reached carried the weight.
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "benchmarks"))
    from bench_sampler import build_demo

    from certpose.sampling.sampler import sample_pose_distribution, seeds_from_mle

    lik, mle, gt = build_demo(seed=seed)
    res = sample_pose_distribution(lik, seeds_from_mle(mle), params=ISParams(resample=10_000), rng=seed)
    assert res.success, res.message
    assert res.weighted.ess >= 1000, res.message
    assert res.weighted.pareto_k() < 0.7
    tilt = np.degrees(np.arccos(np.clip(res.distribution.rotations[:, :, 2] @ gt[:3, 2], -1, 1)))
    assert np.quantile(tilt, 0.95) < 5.0


@pytest.mark.slow
def test_ycbv_mug_mass_in_the_arc_does_not_hang_on_the_seed():
    # YCB-Video 0000/000001, the mug (handle hidden), ground-truth mask: with seed 0 the MLE's
    # poses all lie in the arc, with seed 2 all in the scene's other free run (the handle behind
    # the foam brick). The sampler before the sweeps put 0.80 and 0.00 of its mass in the arc
    # (0.06 and 0.90 in the other run): it stayed in the run its seeds came from.
    import sys
    from pathlib import Path

    from tests.conftest import require_data

    root = require_data("ycbv", "0000")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "benchmarks"))
    from bench_samplers import free_arc_metrics, support_normal, ycbv_problem

    from certpose.sampling.sampler import sample_pose_distribution

    figures = []
    for seed in (0, 2):
        lik, seeds, gt, arc, centre = ycbv_problem(root.parent, "000001", seed)
        res = sample_pose_distribution(lik, seeds, params=ISParams(resample=10_000), rng=seed)
        assert res.success, res.message
        assert res.weighted.ess >= 1000, res.message
        figures.append(free_arc_metrics(res.distribution, gt, arc, centre, support_normal(root.parent, "000001")))
    a, b = figures
    for f in figures:
        # The literal reading's arc is every free run: the two parts together.
        assert f["mass_in_union"] == pytest.approx(f["mass_in_arc"] + f["mass_other_free"])
        assert f["union_coverage"] > 0.5, f
        # The table's normal (fitted to the depth image alone) is 2 deg from the ground truth's
        # axis; the distribution's axis is within 5 deg of either for most of the mass (measured
        # 0.73-0.77 of it).
        assert 1.0 < f["gt_axis_vs_table"] < 3.5, f
        assert min(f["axis_ok_table"], f["axis_ok"]) > 0.65, f
    assert abs(a["mass_in_arc"] - b["mass_in_arc"]) < 0.1, figures
    assert abs(a["mass_other_free"] - b["mass_other_free"]) < 0.1, figures
    assert min(a["mass_in_arc"], b["mass_in_arc"]) > 0.4, figures


@pytest.fixture(scope="module")
def demo_seed1():
    """The demo at seed 1 and ours' distribution on it (shared by the known-answer tests)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "benchmarks"))
    from bench_samplers import demo_problem

    from certpose.sampling.sampler import sample_pose_distribution

    lik, seeds, gt, arc, centre = demo_problem(1)
    res = sample_pose_distribution(lik, seeds, params=ISParams(resample=10_000), rng=1)
    return lik, gt, arc, centre, res


@pytest.mark.slow
def test_demo_marginal_about_the_axis_is_uniform_on_the_exact_hidden_arc(demo_seed1):
    # The demo (its mug sampled by its axial symmetry): every turn about the axis that keeps the
    # handle out of sight gives the scene's image exactly (SyntheticScene.hidden_handle_arc,
    # rendered), so the rotation about the axis should be uniform on that arc. Measured
    # 2026-11-26, seeds 0-4: total variation (5 deg bins) 0.060-0.109 (0.064-0.133 on a later
    # tree), 0.89-0.96 of the mass in
    # the arc (eq. (1) does not see the handle's first 10-15 deg out of hiding, a few mm in
    # front of the surface behind it); Nevergrad DE 0.42-0.86, MCMC 0.16-0.23. The voxel-averaged
    # model (object_from_views(revolution=None)) gives seed 1 a TV of 0.48 and covers 0.55 of it.
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "benchmarks"))
    from bench_samplers import free_arc_metrics, tv_uniform

    _, gt, arc, centre, res = demo_seed1
    assert arc.success and arc.arc[1] - arc.arc[0] > 150.0
    assert res.success and res.weighted.ess >= 1000, res.message
    f = free_arc_metrics(res.distribution, gt, arc, centre)
    assert f["arc_coverage"] >= 0.95 and f["mass_in_arc"] >= 0.9 and f["axis_ok"] >= 0.95, f
    assert tv_uniform(res.distribution, gt, arc) < 0.1


@pytest.mark.slow
def test_demo_marginal_about_the_axis_is_the_targets_exact_marginal(demo_seed1):
    # Issue 11's known answer read as the issue words it: the marginal of the target
    # exp(eq. (1) / T) itself, its other five degrees of freedom integrated at every angle
    # (certpose.sampling.reference.axis_marginal, angles drawn uniformly: it cannot miss part of
    # the arc). Measured 2026-11-26 on seed 1: TV 0.03-0.04 (the reference's own error 0.013 at
    # 200,000 draws, 0.026 at 50,000); the sampler restricted to half of its draws' arc is far.
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "benchmarks"))
    from bench_samplers import AXIS

    from certpose.sampling.plots import axis_angles
    from certpose.sampling.reference import axis_marginal

    lik, gt, _, centre, res = demo_seed1
    exact = axis_marginal(lik, gt, AXIS, temperature=res.temperature, pivot=centre, draws=50_000, rng=0)
    assert exact.ess > 2000 and exact.tv_error < 0.04, (exact.ess, exact.tv_error)
    # The target's arc spans more than 150 deg: the comparison is not about one peak.
    assert np.sum(exact.mass > 0.25 * exact.mass.max()) * 5.0 > 150.0
    tv, outside = exact.compare(res.distribution)
    assert tv < 0.1 and outside < 0.05, (tv, outside)
    d = res.distribution
    half = axis_angles(d.rotations, AXIS, gt) < np.median(axis_angles(d.rotations, AXIS, gt))
    wrong = PoseDistribution(d.rotations[half], d.translations[half], d.weights[half] / d.weights[half].sum())
    assert exact.compare(wrong)[0] > 0.3


def test_fixed_share_sets_a_seeds_initial_share():
    # Two seeds of equal target value share the initial mixture equally; a fixed share of 5% for
    # the second leaves the first the rest; with a third seed far below the other two, the seeds
    # without a fixed share split the rest by their values (the far one floored at 1%). One
    # round: the proposal is the initial mixture.
    R0 = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    t0 = np.array([0.1, 0.0, 0.6])
    target = _target_gaussian(R0, t0, np.array([0.02, 0.02, 0.6, 0.003, 0.003, 0.003]))
    seeds = np.tile(np.eye(4), (3, 1, 1))
    for k, a in enumerate([0.3, -0.3, 0.0]):
        seeds[k, :3, :3] = R0 @ Rotation.from_rotvec([0, 0, a]).as_matrix()
        seeds[k, :3, 3] = t0
    seeds[2, :3, 3] += [0.05, 0, 0]  # about 140 nats below
    p = ISParams(draws=200, rounds=1, temperature=1.0)
    free = importance_sample(target, seeds[:2], params=p, rng=0)
    np.testing.assert_allclose(free.proposal.weights, [0.5, 0.5])
    fixed = importance_sample(target, seeds[:2], params=p, rng=0, fixed_share=[np.nan, 0.05])
    np.testing.assert_allclose(fixed.proposal.weights, [0.95, 0.05])
    three = importance_sample(target, seeds, params=p, rng=0, fixed_share=[np.nan, 0.2, np.nan])
    np.testing.assert_allclose(three.proposal.weights, [0.8 / 1.01, 0.2, 0.8 * 0.01 / 1.01])
    for bad in ([np.nan, 0.0], [0.5, 0.5], [np.nan, 1.0], [np.nan]):
        with pytest.raises(ValueError, match="fixed_share"):
            importance_sample(target, seeds[:2], params=p, rng=0, fixed_share=bad)


def _tilt_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle (deg) between the object z axes (the mug's axis) of two rotations."""
    return float(np.degrees(np.arccos(np.clip(Ra[:, 2] @ Rb[:, 2], -1.0, 1.0))))


@pytest.mark.slow
def test_half_turns_of_a_real_model_are_half_turns_refined():
    # The YCB-Video mug (its real model) in 0000/000001 at the ground truth: the three half
    # turns about the model's principal axes through its centroid, then refined on eq. (1).
    from certpose.model.likelihood import PoseLikelihood
    from certpose.sampling.sampler import half_turn_seeds, principal_half_turns
    from tests.conftest import mug_on_0000

    s, gt, _, _ = mug_on_0000("000001")
    lik = PoseLikelihood(s.scene, s.classification, s.object_model)
    T = np.asarray(gt, dtype=np.float64)
    H = principal_half_turns(lik, T)
    pts = lik._points
    c = pts.mean(axis=0)
    _, V = np.linalg.eigh(np.cov((pts - c).T))
    for i in range(3):
        D = np.linalg.inv(T) @ H[i]  # the turn in the object frame
        np.testing.assert_allclose(np.trace(D[:3, :3]), -1.0, atol=1e-9)  # angle pi
        np.testing.assert_allclose(D[:3, :3] @ V[:, i], V[:, i], atol=1e-9)  # about principal axis i
        np.testing.assert_allclose(D[:3, :3] @ c + D[:3, 3], c, atol=1e-12)  # through the centroid
        np.testing.assert_allclose(D @ D, np.eye(4), atol=1e-9)
    # In the scene: a half turn about v takes the mug's axis z to 2 (v.z) v - z, so the axis tilts
    # by arccos(2 (v.z)^2 - 1) (the handle tips the principal axes 10-60 deg off the mug's axis).
    for i in range(3):
        expect = np.degrees(np.arccos(2 * V[2, i] ** 2 - 1))
        assert _tilt_deg(H[i, :3, :3], T[:3, :3]) == pytest.approx(expect, abs=1e-6)
    P, v = half_turn_seeds(lik, T)
    np.testing.assert_allclose(v, lik(P))
    before = lik(H)
    assert np.all(v >= before - 1e-6), (v, before)
    assert np.any(v > before + 1.0)  # refinement moved them uphill
    # Refined locally: each stays within 30 deg and one model radius of its half turn (measured
    # 2026-11-26: up to 11 deg and 4 cm, the mug's radius about its centroid being 7 cm).
    radius = np.linalg.norm(pts - c, axis=1).max()
    for Hi, Pi in zip(H, P, strict=True):
        ang = np.degrees(np.linalg.norm(Rotation.from_matrix(Hi[:3, :3].T @ Pi[:3, :3]).as_rotvec()))
        assert ang < 30.0 and np.linalg.norm(Hi[:3, 3] - Pi[:3, 3]) < radius, (ang, Hi[:3, 3] - Pi[:3, 3])


@pytest.mark.slow
def test_the_upside_down_basin_of_a_bottomless_mug_is_drawn_not_hit():
    # The demo at seed 4 with a model from views above the mug only: it lacks its bottom, so
    # upside down it is nearly itself. The upside-down basin scored 4 tempered nats below the MLE
    # when no seed reached it, and 67 tail draws carried 5% of the weight, one of them 4% (ESS
    # 563 of 10,000); the half-turn seeds were added for it. The MLE's refined principal turns
    # now report that basin among its modes (within a few nats), so the sampler's own seeds
    # reach it: it is drawn by many draws, none holding 1% of the weight.
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "benchmarks"))
    from bench_sampler import build_demo

    from certpose.sampling.sampler import sample_pose_distribution, seeds_from_mle

    lik, mle, gt = build_demo(seed=4, elevation_deg=30.0, ring_modes=False)
    seeds = seeds_from_mle(mle)
    assert sum(_tilt_deg(S[:3, :3], gt[:3, :3]) > 150.0 for S in seeds) >= 1
    res = sample_pose_distribution(lik, seeds, params=ISParams(resample=10_000), rng=4)
    assert res.success and res.weighted.ess >= 2000, res.message
    assert res.weighted.pareto_k() < 0.7
    w = res.weighted.weights
    tilt = np.degrees(np.arccos(np.clip(res.weighted.rotations[:, :, 2] @ gt[:3, 2], -1, 1)))
    # Without its bottom the upturned mug differs from the upright one only where eq. (1)'s
    # visibility and free-space tests tell them apart: it takes a share of the mass.
    assert np.count_nonzero(tilt > 90.0) >= 50 and 0.0 < w[tilt > 90.0].sum() < 0.6
    assert w.max() < 0.01
