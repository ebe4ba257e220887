"""PoseDistribution: weights, ESS, Pareto-k, resampling, tangent moments, .npz round trip."""

import gc
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose.sampling.distribution import PoseDistribution


def _particles(n, rng=0):
    rng = np.random.default_rng(rng)
    R = Rotation.random(n, random_state=1).as_matrix()
    t = rng.normal(size=(n, 3))
    return R, t


def test_ess_hand_computed():
    R, t = _particles(4)
    d = PoseDistribution(R, t, np.array([0.5, 0.25, 0.125, 0.125]))
    # 1 / (0.25 + 0.0625 + 2 * 0.015625) = 1 / 0.34375
    assert d.ess == pytest.approx(1 / 0.34375)
    assert PoseDistribution(R, t, np.full(4, 0.25)).ess == pytest.approx(4.0)


def test_from_log_weights_normalises():
    R, t = _particles(3)
    d = PoseDistribution.from_log_weights(R, t, np.log([1.0, 2.0, 5.0]) + 1000.0)
    np.testing.assert_allclose(d.weights, [0.125, 0.25, 0.625])


def test_pareto_k_uniform_vs_heavy_tail():
    rng = np.random.default_rng(3)
    n = 2000
    R, t = _particles(n)
    # Bounded log-weights (light tail): k well below 0.5.
    lw_light = 0.1 * rng.random(n)
    assert PoseDistribution.from_log_weights(R, t, lw_light).pareto_k() < 0.5
    # Log-weights of a Pareto(k = 1) tail: ratios w = U^-1, so PSIS must report k near 1.
    lw = -np.log(rng.random(n))
    k = PoseDistribution.from_log_weights(R, t, lw).pareto_k()
    assert 0.7 < k < 1.3


def test_resample_frequencies_match_weights():
    R, t = _particles(3)
    w = np.array([0.6, 0.3, 0.1])
    r = PoseDistribution(R, t, w).resample(10_000, rng=0)
    counts = [np.sum(np.all(r.translations == t[i], axis=1)) for i in range(3)]
    # Systematic resampling: each count is within one of n * w.
    np.testing.assert_array_less(np.abs(np.array(counts) - 10_000 * w), 1.0 + 1e-9)
    assert r.ess == pytest.approx(10_000)
    assert r.log_weights is None
    with pytest.raises(ValueError, match="raw `log_weights`"):
        r.pareto_k()


def test_mean_and_covariance_recover_gaussian():
    rng = np.random.default_rng(5)
    n = 20_000
    R0 = Rotation.from_rotvec([0.3, -1.0, 0.5]).as_matrix()
    t0 = np.array([0.1, 0.2, 0.8])
    sd = np.array([0.05, 0.1, 0.02, 0.01, 0.003, 0.02])
    X = rng.normal(size=(n, 6)) * sd
    R = R0 @ Rotation.from_rotvec(X[:, :3]).as_matrix()
    d = PoseDistribution(R, t0 + X[:, 3:], np.full(n, 1.0 / n))
    Rm, tm, cov = d.mean_and_covariance()
    assert np.linalg.norm(Rotation.from_matrix(R0.T @ Rm).as_rotvec()) < 3e-3
    np.testing.assert_allclose(tm, t0, atol=1e-3)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), sd, rtol=0.05)


def test_npz_round_trip(tmp_path):
    R, t = _particles(5)
    d = PoseDistribution.from_log_weights(R, t, np.arange(5.0))
    d.save(tmp_path / "p.npz")
    e = PoseDistribution.load(tmp_path / "p.npz")
    for name in ("rotations", "translations", "weights", "log_weights"):
        np.testing.assert_array_equal(getattr(e, name), getattr(d, name))
    with pytest.raises(ValueError, match="Cannot read"):
        PoseDistribution.load(tmp_path / "missing.npz")
    # A .npy file (np.load gives a bare array) and a cut archive (BadZipFile, the file left
    # open): the same one-line ValueError naming the file.
    np.save(tmp_path / "p.npy", R)
    cut = tmp_path / "cut.npz"
    cut.write_bytes((tmp_path / "p.npz").read_bytes()[:300])
    for bad in (tmp_path / "p.npy", cut):
        with warnings.catch_warnings():
            warnings.simplefilter("error", ResourceWarning)
            with pytest.raises(ValueError, match=f"Cannot read particle file .*{bad.name}.*not a .npz"):
                PoseDistribution.load(bad)
            gc.collect()  # an unclosed file warns when collected


@pytest.mark.parametrize(
    "weights, match",
    [
        ([0.5, 0.5, 0.0], "positive"),
        ([1.5, -0.5, 0.0], "positive"),
        ([np.nan, 0.5, 0.5], "NaN"),
        ([0.2, 0.2, 0.2], "sum to 1"),
        ([0.5, 0.5], r"shape \(3,\)"),
    ],
)
def test_bad_weights(weights, match):
    R, t = _particles(3)
    with pytest.raises(ValueError, match=match):
        PoseDistribution(R, t, np.array(weights))


def test_from_log_weights_and_resample_name_their_argument():
    R, t = _particles(3)
    # A length mismatch was reported as one of `weights` (computed inside).
    with pytest.raises(ValueError, match=r"`log_weights` to have shape \(3,\)"):
        PoseDistribution.from_log_weights(R, t, np.zeros(5))
    d = PoseDistribution.from_log_weights(R, t, np.zeros(3))
    # resample(1.5) drew 1 particle, resample(0) and resample(-1) were refused.
    for n in (1.5, 0, -1):
        with pytest.raises(ValueError, match="`n` to be a positive integer"):
            d.resample(n)
    assert len(d.resample(np.int64(4), rng=0)) == 4 and len(d.resample(rng=0)) == 3


def test_bad_particles():
    R, t = _particles(3)
    with pytest.raises(ValueError, match="non-empty"):
        PoseDistribution(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0))
    R_bad = R.copy()
    R_bad[1] *= 1.1
    with pytest.raises(ValueError, match=r"`rotations\[1\]` is not a rotation"):
        PoseDistribution(R_bad, t, np.full(3, 1 / 3))
    with pytest.raises(ValueError, match="not a rotation"):
        PoseDistribution(-R, t, np.full(3, 1 / 3))
    with pytest.raises(ValueError, match=r"shape \(3, 3\)"):
        PoseDistribution(R, t[:, :2], np.full(3, 1 / 3))
    with pytest.raises(ValueError, match="NaN"):
        PoseDistribution.from_log_weights(R, t, [0.0, np.nan, 1.0])


def test_frozen():
    R, t = _particles(2)
    d = PoseDistribution(R, t, np.full(2, 0.5))
    with pytest.raises(AttributeError):
        d.weights = np.ones(2)
    with pytest.raises(ValueError):
        d.weights[0] = 1.0


def test_log_density_matches_smoothed_gaussian():
    rng = np.random.default_rng(7)
    n = 5000
    sd = np.array([0.02, 0.03, 0.01, 0.004, 0.002, 0.003])
    X = rng.normal(size=(n, 6)) * sd
    R0 = Rotation.from_rotvec([0.2, 0.1, -0.4]).as_matrix()
    t0 = np.array([0.0, 0.1, 0.7])
    d = PoseDistribution(
        R0 @ Rotation.from_rotvec(X[:, :3]).as_matrix(), t0 + X[:, 3:], np.full(n, 1 / n)
    )
    # A Gaussian KDE of a Gaussian is, in expectation, the Gaussian with covariance (1 + h^2) C.
    h2 = n ** (-0.2)
    expected = -3 * np.log(2 * np.pi) - np.sum(np.log(sd)) - 3 * np.log(1 + h2)
    assert d.log_density(R0, t0) == pytest.approx(expected, abs=0.15)
    # Far from the particles the density is tiny.
    assert d.log_density(R0, t0 + 0.05) < expected - 100


def test_modes_two_clusters_with_their_mass():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    n = 3000
    # Two pose clusters 90 deg apart about z, masses 0.7 / 0.3, plus an arc inside the first.
    a = np.where(np.arange(n) < 2100, rng.uniform(-0.5, 0.5, n), np.pi / 2 + rng.normal(0, 0.01, n))
    R = Rotation.from_rotvec(np.outer(a, [0, 0, 1])).as_matrix()
    t = rng.normal(0, 0.001, (n, 3))
    d = PoseDistribution(R, t, np.full(n, 1.0 / n))
    modes = d.modes(max_points=1000)
    assert len(modes) == 2
    assert modes[0].mass == pytest.approx(0.7) and modes[1].mass == pytest.approx(0.3)
    assert modes[0].num_particles + modes[1].num_particles == n
    ang = Rotation.from_matrix(modes[1].rotation).as_rotvec()
    np.testing.assert_allclose(ang, [0, 0, np.pi / 2], atol=0.01)
    assert modes[0].covariance[2, 2] == pytest.approx(1 / 12, rel=0.1)  # uniform on [-0.5, 0.5]
    with pytest.raises(ValueError, match="rotation_scale"):
        d.modes(rotation_scale=0.0)


def _gaussian_particles(n, sd, rng):
    R0 = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    t0 = np.array([0.1, -0.05, 0.6])
    X = rng.normal(size=(n, 6)) * sd
    R = R0 @ Rotation.from_rotvec(X[:, :3]).as_matrix()
    return PoseDistribution(R, t0 + X[:, 3:], np.full(n, 1.0 / n)), R0, t0


def test_credible_level_of_gaussian_follows_chi2():
    from scipy.stats import chi2

    rng = np.random.default_rng(3)
    sd = np.array([0.02, 0.02, 0.02, 0.004, 0.004, 0.004])
    d, R0, t0 = _gaussian_particles(1000, sd, rng)
    for r in (1.0, 2.0, 3.0):
        # Queries at Mahalanobis radius r. The kernel density is (in expectation) the Gaussian
        # widened by (1 + h^2), a monotone function of the radius: the particles denser than a
        # query are those inside radius r, a chi-square(6) fraction. One query's level is noisy
        # (sd ~0.08 at 1,000 particles): average over directions.
        levels = []
        for _ in range(12):
            u = rng.normal(size=6)
            x = r * sd * u / np.linalg.norm(u)
            levels.append(d.credible_level(R0 @ Rotation.from_rotvec(x[:3]).as_matrix(), t0 + x[3:]))
        assert abs(np.mean(levels) - chi2.cdf(r * r, df=6)) < 0.08, (r, np.mean(levels))


def test_credible_level_is_uniform_for_draws_of_the_distribution():
    from scipy.stats import kstest

    rng = np.random.default_rng(4)
    sd = np.array([0.05, 0.01, 0.03, 0.002, 0.01, 0.004])
    d, R0, t0 = _gaussian_particles(1500, sd, rng)
    # Fresh draws from the same law: their levels are uniform on [0, 1] up to the kernel's widening.
    q, _, _ = _gaussian_particles(60, sd, np.random.default_rng(5))
    levels = [d.credible_level(R, t) for R, t in zip(q.rotations, q.translations, strict=True)]
    assert kstest(levels, "uniform").pvalue > 0.01
    # A pose far outside is outside every region; the mode itself is inside the smallest.
    assert d.credible_level(R0 @ Rotation.from_rotvec([0.5, 0, 0]).as_matrix(), t0) == 1.0
    assert d.credible_level(R0, t0) < 0.05


def test_credible_level_bad_input():
    d, R0, t0 = _gaussian_particles(50, np.full(6, 0.01), np.random.default_rng(0))
    with pytest.raises(ValueError, match="not a rotation"):
        d.credible_level(2.0 * R0, t0)
    with pytest.raises(ValueError, match="max_particles"):
        d.credible_level(R0, t0, max_particles=0)


def test_kernel_of_resampled_set_counts_distinct_particles():
    # Resampling repeats particles: the bandwidth must not shrink as if every copy were new.
    rng = np.random.default_rng(9)
    d, R0, t0 = _gaussian_particles(400, np.full(6, 0.01), rng)
    big = d.resample(20_000, rng=1)
    assert big.ess == pytest.approx(20_000)
    assert big._kernel_count() <= 400
    # Same kernel (bandwidth x covariance) as the set it was drawn from, to sampling error.
    np.testing.assert_allclose(big._kernel()[0], d._kernel()[0], rtol=0.1, atol=1e-4)


def _two_modes(rng, n_a=600, n_b=400):
    """Two Gaussian clouds 90 deg and 30 cm apart, masses 0.6 / 0.4 (equal particle weights)."""
    sd = np.array([0.02, 0.03, 0.01, 0.004, 0.002, 0.003])
    d_a, R0, t0 = _gaussian_particles(n_a, sd, rng)
    R1 = R0 @ Rotation.from_rotvec([0.0, np.pi / 2, 0.0]).as_matrix()
    X = rng.normal(size=(n_b, 6)) * sd[[2, 0, 1, 5, 3, 4]]
    R_b = R1 @ Rotation.from_rotvec(X[:, :3]).as_matrix()
    t_b = t0 + [0.3, 0.0, 0.0] + X[:, 3:]
    n = n_a + n_b
    both = PoseDistribution(np.concatenate([d_a.rotations, R_b]),
                            np.concatenate([d_a.translations, t_b]), np.full(n, 1.0 / n))
    return both, d_a, R0, t0


def test_log_density_of_two_modes_is_each_modes_density_times_its_mass():
    # One covariance over both modes (90 deg and 30 cm wide) would smooth each mode away; per
    # mode, the density at a mode's centre is that mode's own kernel density times its mass.
    both, d_a, R0, t0 = _two_modes(np.random.default_rng(11))
    assert len(both.modes()) == 2
    expected = np.log(0.6) + d_a.log_density(R0, t0)
    assert both.log_density(R0, t0) == pytest.approx(expected, abs=1e-9)
    # And the lone mode's density is its Gaussian's, widened by Scott's factor (as above).
    sd = np.array([0.02, 0.03, 0.01, 0.004, 0.002, 0.003])
    h2 = 600 ** (-0.2)
    gauss = -3 * np.log(2 * np.pi) - np.sum(np.log(sd)) - 3 * np.log(1 + h2)
    assert d_a.log_density(R0, t0) == pytest.approx(gauss, abs=0.3)


def test_log_density_of_an_arc_about_an_offset_axis():
    # A hidden handle: rotations spread uniformly over 90 deg about an axis 5 cm from the object
    # origin, with small tilts and a small spread of the axis point. The origin's translation
    # sweeps a curved 5 cm arc; in the chart of the axis point (the mode's pivot) the mode is a
    # straight, thin slab, and the density at its middle is the slab's.
    rng = np.random.default_rng(12)
    n, width = 4000, np.pi / 2
    c = np.array([0.05, 0.0, 0.0])  # a point on the axis, object frame
    s_tilt, s_t = 0.01, 0.001
    phi = rng.uniform(-width / 2, width / 2, n)
    tilt = np.c_[rng.normal(0, s_tilt, (n, 2)), np.zeros(n)]
    R0 = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    R = R0 @ Rotation.from_rotvec(np.outer(phi, [0, 0, 1])).as_matrix() @ Rotation.from_rotvec(tilt).as_matrix()
    axis_point = np.array([0.1, 0.0, 0.6]) + rng.normal(0, s_t, (n, 3))
    t = axis_point - R @ c
    d = PoseDistribution(R, t, np.full(n, 1.0 / n))
    # Exact density at the middle of the slab (phi = 0, no tilt, axis point at its mean): uniform
    # along phi, Gaussian in the two tilts and the axis point's three coordinates; the KDE widens
    # the five Gaussian directions by (1 + h^2).
    h2 = n ** (-0.2)
    exact = (-np.log(width) - np.log(2 * np.pi * s_tilt**2) - 1.5 * np.log(2 * np.pi * s_t**2)
             - 2.5 * np.log(1 + h2))
    t_mid = np.array([0.1, 0.0, 0.6]) - R0 @ c
    assert d.log_density(R0, t_mid) == pytest.approx(exact, abs=0.3)


def test_credible_level_of_two_modes():
    from scipy.stats import kstest

    rng = np.random.default_rng(13)
    both, _, R0, t0 = _two_modes(rng)
    # Fresh draws of the same two-mode law: uniform levels.
    fresh, _, _, _ = _two_modes(np.random.default_rng(14), 36, 24)
    levels = [both.credible_level(R, t) for R, t in zip(fresh.rotations, fresh.translations, strict=True)]
    assert kstest(levels, "uniform").pvalue > 0.01
    # The heavier mode's centre is inside the smallest region; between the modes, outside all.
    assert both.credible_level(R0, t0) < 0.05
    assert both.credible_level(R0, t0 + [0.15, 0.0, 0.0]) == 1.0


def test_log_density_bad_input():
    d, R0, t0 = _gaussian_particles(50, np.full(6, 0.01), np.random.default_rng(0))
    with pytest.raises(ValueError, match="not a rotation"):
        d.log_density(2.0 * R0, t0)
    with pytest.raises(ValueError, match="`R`"):
        d.log_density(R0[:2], t0)
    with pytest.raises(ValueError, match="`t`"):
        d.log_density(R0, [0.0, np.nan, 0.0])
    with pytest.raises(ValueError, match="`t`"):
        d.credible_level(R0, [0.0, 0.0])


def test_model_error_kernel_spreads_each_particle_about_the_centre() -> None:
    from scipy.spatial.transform import Rotation

    from certpose.sampling import PoseDistribution

    R0 = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    t0 = np.array([0.1, -0.05, 0.8])
    d = PoseDistribution(np.repeat(R0[None], 2, 0), np.repeat(t0[None], 2, 0), np.array([0.25, 0.75]))
    c = np.array([0.02, 0.03, -0.01])
    e = d.with_model_error(np.radians(4.0), 0.0, centre=c, copies=2000, rng=0)
    assert len(e) == 4000 and e.weights.sum() == pytest.approx(1.0)
    assert e.weights[:2000].sum() == pytest.approx(0.25)
    # Turned about the centre: its image does not move without translation noise.
    np.testing.assert_allclose(e.rotations @ c + e.translations, np.tile(R0 @ c + t0, (4000, 1)), atol=1e-12)
    # The body-frame rotation vectors have the kernel's spread per axis.
    w = Rotation.from_matrix(np.einsum("ji,njk->nik", R0, e.rotations)).as_rotvec()
    np.testing.assert_allclose(w.std(axis=0), np.radians(4.0), rtol=0.1)
    f = d.with_model_error(0.0, 0.003, centre=c, copies=2000, rng=1)
    np.testing.assert_allclose((f.translations - t0).std(axis=0), 0.003, rtol=0.1)
    np.testing.assert_array_equal(f.rotations, np.repeat(R0[None], 4000, 0))
    with pytest.raises(ValueError, match="rotation_sigma"):
        d.with_model_error(-1.0, 0.0)
    with pytest.raises(ValueError, match="copies"):
        d.with_model_error(0.1, 0.0, copies=0)
    # Student t kernel: per particle one scale for rotation and translation, the translation's
    # marginal a t with dof degrees of freedom (tails far heavier than the Gaussian's).
    from scipy import stats

    g = d.with_model_error(np.radians(2.0), 0.002, centre=c, copies=20000, dof=3.0, rng=2)
    x = (g.translations - (R0 @ c + t0) + np.einsum("nij,j->ni", g.rotations, c)) / 0.002
    assert stats.kstest(x[:, 0], stats.t(3.0).cdf).pvalue > 0.01
    rv = np.linalg.norm(Rotation.from_matrix(np.einsum("ji,njk->nik", R0, g.rotations)).as_rotvec(), axis=1)
    tn = np.linalg.norm(x, axis=1)
    assert np.corrcoef(rv, tn)[0, 1] > 0.3  # one scale draw for both
    for bad in (0.0, -2.0, float("nan")):
        with pytest.raises(ValueError, match="dof"):
            d.with_model_error(0.1, 0.0, dof=bad)


def test_model_error_kernel_splits_tilt_and_spin_about_an_axis_of_revolution() -> None:
    from scipy.spatial.transform import Rotation

    from certpose.sampling import PoseDistribution

    R0 = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    t0 = np.array([0.1, -0.05, 0.8])
    d = PoseDistribution(R0[None], t0[None], np.ones(1))
    axis = np.array([1.0, 2.0, 2.0]) / 3.0  # object frame, not a coordinate axis
    c = np.array([0.01, -0.02, 0.03])
    e = d.with_model_error(np.radians(1.0), 0.0, centre=c, copies=20000, axis=3.0 * axis,
                           spin_sigma=np.radians(5.0), rng=0)
    w = Rotation.from_matrix(np.einsum("ji,njk->nik", R0, e.rotations)).as_rotvec()
    spin = w @ axis
    tilt_part = w - np.outer(spin, axis)
    assert spin.std() == pytest.approx(np.radians(5.0), rel=0.05)
    # Two tilt components of 1 deg each: E|tilt|^2 = 2 sigma^2.
    assert np.sqrt(np.mean(np.sum(tilt_part**2, axis=1))) == pytest.approx(np.sqrt(2) * np.radians(1.0), rel=0.05)
    # The axis itself tilts by the tilt part only (the spin leaves it in place).
    tilt = np.arccos(np.clip((e.rotations @ axis) @ (R0 @ axis), -1.0, 1.0))
    assert np.quantile(tilt, 0.99) < np.radians(3.5)
    # Without an axis the same call is isotropic: the spin would tilt it.
    f = d.with_model_error(np.radians(5.0), 0.0, centre=c, copies=20000, rng=0)
    assert np.quantile(np.arccos(np.clip((f.rotations @ axis) @ (R0 @ axis), -1.0, 1.0)), 0.5) > np.radians(5.0)
    np.testing.assert_allclose(e.rotations @ c + e.translations, np.tile(R0 @ c + t0, (20000, 1)), atol=1e-12)
    with pytest.raises(ValueError, match="spin_sigma` needs `axis"):
        d.with_model_error(0.1, 0.0, spin_sigma=0.1)
    with pytest.raises(ValueError, match="spin_sigma"):
        d.with_model_error(0.1, 0.0, axis=axis, spin_sigma=-0.1)
    with pytest.raises(ValueError, match=r"`axis` to have shape \(3,\)"):
        d.with_model_error(0.1, 0.0, axis=[1.0, 0.0])
    with pytest.raises(ValueError, match="non-zero"):
        d.with_model_error(0.1, 0.0, axis=[0.0, 0.0, 0.0])
