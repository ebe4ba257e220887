"""Marginals (wrap-around KDE, rotation about an object axis) and the PNG of their plot."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose.sampling import PoseDistribution
from certpose.sampling.chart import from_chart
from certpose.sampling.plots import (
    axis_angles,
    euler_angles,
    marginal_kde,
    marginals,
    plot_marginals,
)

R0 = Rotation.from_euler("ZYX", [170.0, 10.0, -30.0], degrees=True).as_matrix()
T0 = np.eye(4)
T0[:3, :3], T0[:3, 3] = R0, [0.05, -0.02, 0.7]


def _dist(n=2000, spin=0.6):
    x = np.random.default_rng(0).normal(size=(n, 6)) * [0.01, 0.01, spin, 0.002, 0.002, 0.003]
    T = from_chart(x, T0)
    return PoseDistribution(T[:, :3, :3], T[:, :3, 3], np.full(n, 1.0 / n)), x


def test_periodic_kde_does_not_split_mass_at_the_seam():
    rng = np.random.default_rng(1)
    v = np.pi - 0.1 + 0.2 * rng.normal(size=4000)  # straddles +-pi
    w = rng.random(4000) + 0.5
    g = np.linspace(-np.pi, np.pi, 4001)
    dens = marginal_kde(((v + np.pi) % (2 * np.pi)) - np.pi, w, g, periodic=True)
    assert abs(np.trapezoid(dens, g) - 1.0) < 1e-3
    # The same density as a plain KDE of the unwrapped values, shifted by a turn.
    plain = marginal_kde(v, w, np.where(g < 0, g + 2 * np.pi, g))
    np.testing.assert_allclose(dens, plain, atol=2e-3 * plain.max())
    # Continuous across the seam.
    assert abs(dens[0] - dens[-1]) < 1e-6 * dens.max()


def test_axis_angle_is_the_spin_about_the_axis():
    d, x = _dist()
    a = axis_angles(d.rotations, [0, 0, 2.0], T0)
    # Small tilts barely change the twist about z.
    np.testing.assert_allclose(a, x[:, 2], atol=5e-3)
    R = T0[:3, :3] @ Rotation.from_rotvec([[0, 0, 3.0]]).as_matrix()
    np.testing.assert_allclose(axis_angles(R, [0, 0, 1], T0), [3.0], atol=1e-9)
    np.testing.assert_allclose(euler_angles(R0[None])[0], np.radians([-30.0, 10.0, 170.0]))


def test_marginals_mark_the_truth_and_integrate_to_one():
    d, _ = _dist()
    ms = marginals(d, axis=(0, 0, 1), T_gt=T0)
    assert [m.name for m in ms][:6] == ["roll", "pitch", "yaw", "x", "y", "z"]
    for m in ms:
        assert m.truth is not None and np.all(np.isfinite(m.density))
        area = np.trapezoid(m.density, m.grid)
        assert 0.97 < area < 1.01, (m.name, area)
    yaw = ms[2]
    assert abs(((yaw.truth - 170.0) + 180) % 360 - 180) < 1e-6
    assert abs(ms[3].truth - 5.0) < 1e-9  # cm
    assert abs(ms[6].truth) < 1e-9  # the reference is the truth


def test_plot_written(tmp_path):
    d, _ = _dist()
    out = plot_marginals(d, tmp_path / "m.png", axis=(0, 0, 1), T_gt=T0, size=(8, 4), dpi=50)
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    import struct

    w, h = struct.unpack(">II", data[16:24])
    assert (w, h) == (400, 200)
    out2 = plot_marginals(d, tmp_path / "n.png")  # no truth, no axis
    assert out2.stat().st_size > 1000


def test_a_single_particle_still_plots(tmp_path):
    d = PoseDistribution(R0[None], T0[:3, 3][None], np.ones(1))
    assert all(np.all(np.isfinite(m.density)) for m in marginals(d, axis=(0, 0, 1)))
    assert plot_marginals(d, tmp_path / "one.png", axis=(0, 0, 1)).stat().st_size > 0


def test_bad_input(tmp_path):
    d, _ = _dist(100)
    with pytest.raises(TypeError, match="PoseDistribution"):
        marginals(np.zeros((3, 4, 4)))
    with pytest.raises(ValueError, match="axis"):
        marginals(d, axis=(0, 0, 0))
    with pytest.raises(ValueError, match="T_gt"):
        marginals(d, T_gt=np.diag([1.0, 1, -1, 1]))
    with pytest.raises(OSError, match="does not exist"):
        plot_marginals(d, tmp_path / "missing" / "m.png")
    with pytest.raises(ValueError, match="weights"):
        marginal_kde([0.0, 1.0], [1.0, -1.0], [0.0])
    with pytest.raises(ValueError, match="NaN"):
        marginal_kde([0.0, np.nan], [1.0, 1.0], [0.0])
    with pytest.raises(ValueError, match="non-empty"):
        marginal_kde([], [], [0.0])


def _greenish(path):
    import matplotlib.image

    img = matplotlib.image.imread(str(path))[..., :3]
    return int(np.count_nonzero((img[..., 1] > img[..., 0] + 0.04) & (img[..., 1] > img[..., 2] + 0.04)))


def test_plot_shades_the_arcs(tmp_path):
    d, _ = _dist()
    plain = plot_marginals(d, tmp_path / "plain.png", axis=(0, 0, 1), T_gt=T0)
    # One arc inside the panel and one across +-180 deg (ending above 180).
    shaded = plot_marginals(d, tmp_path / "arc.png", axis=(0, 0, 1), T_gt=T0,
                            arcs=[(-30.0, 20.0), (170.0, 200.0)], arcs_label="handle hidden")
    assert _greenish(plain) == 0
    assert _greenish(shaded) > 1000
    with pytest.raises(ValueError, match="axis"):
        plot_marginals(d, tmp_path / "x.png", arcs=[(-30.0, 20.0)])
    with pytest.raises(ValueError, match=r"arcs\[1\]"):
        plot_marginals(d, tmp_path / "x.png", axis=(0, 0, 1), arcs=[(-30.0, 20.0), (10.0, -10.0)])
    with pytest.raises(ValueError, match=r"arcs\[0\]"):
        plot_marginals(d, tmp_path / "x.png", axis=(0, 0, 1), arcs=[(np.nan, 20.0)])
