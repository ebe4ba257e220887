"""The exact marginal about an axis (certpose.sampling.reference): against quadrature and Haar draws."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from certpose.sampling.distribution import PoseDistribution
from certpose.sampling.plots import axis_angles
from certpose.sampling.reference import axis_marginal, swing_angles

AXIS = np.array([0.2, -0.3, 1.0]) / np.linalg.norm([0.2, -0.3, 1.0])
T_REF = np.eye(4)
T_REF[:3, :3] = Rotation.random(random_state=3).as_matrix()
T_REF[:3, 3] = [0.1, -0.2, 0.7]
PIVOT = np.array([0.01, 0.02, -0.03])
MAX_SWING = 150.0


def _sigma(theta):
    return np.radians(10.0 + 35.0 * (1.0 + np.cos(theta)))  # the swing's width follows the angle


def _target(T):
    # Rotation part: 0.7 cos(theta) - swing^2 / (2 sigma(theta)^2); the pivot's offset a 2-mm
    # Gaussian (its integral is the same at every angle).
    R = T[:, :3, :3]
    th, sw = axis_angles(R, AXIS, T_REF), swing_angles(R, AXIS, T_REF)
    p = np.einsum("nij,j->ni", R, PIVOT) + T[:, :3, 3] - (T_REF[:3, :3] @ PIVOT + T_REF[:3, 3])
    return 0.7 * np.cos(th) - sw**2 / (2 * _sigma(th) ** 2) - (p**2).sum(axis=1) / (2 * 0.002**2)


def _quadrature(edges_deg, jacobian=True):
    # m(theta) = e^{0.7 cos theta} * 2 pi * int_0^smax exp(-r^2 / 2 sigma^2) (sin r or r) dr
    th = np.radians(np.arange(-180.0, 180.0, 0.1) + 0.05)
    r = np.linspace(0.0, math.radians(MAX_SWING), 3001)
    g = np.exp(-r[None] ** 2 / (2 * _sigma(th)[:, None] ** 2)) * (np.sin(r) if jacobian else r)[None]
    m = np.exp(0.7 * np.cos(th)) * np.trapezoid(g, r, axis=1)
    h, _ = np.histogram(np.degrees(th), edges_deg, weights=m)
    return h / h.sum()


@pytest.mark.slow
def test_marginal_matches_quadrature_and_haar_draws():
    m = axis_marginal(_target, T_REF, AXIS, pivot=PIVOT, max_swing_deg=MAX_SWING, bin_deg=10.0,
                      draws=200_000, rng=1)
    assert m.mass.shape == (36,) and abs(m.mass.sum() - 1.0) < 1e-12
    exact = _quadrature(m.edges_deg)
    tv = 0.5 * np.abs(m.mass - exact).sum()
    assert tv < 3 * m.tv_error and m.tv_error < 0.02, (tv, m.tv_error)
    # Without the Haar measure's sin|s| / |s| the answer differs by more than the estimate's error.
    assert 0.5 * np.abs(_quadrature(m.edges_deg, jacobian=False) - exact).sum() > 3 * m.tv_error
    # Haar-uniform rotations weighted by the target's rotation part: no shared parametrisation.
    R = Rotation.random(1_000_000, random_state=5).as_matrix()
    th, sw = axis_angles(R, AXIS, T_REF), swing_angles(R, AXIS, T_REF)
    w = np.exp(0.7 * np.cos(th) - sw**2 / (2 * _sigma(th) ** 2)) * (sw <= math.radians(MAX_SWING))
    h, _ = np.histogram(np.degrees(th), m.edges_deg, weights=w)
    assert 0.5 * np.abs(h / h.sum() - m.mass).sum() < 3 * m.tv_error + 0.01
    # The mass with the axis within 20 deg (the pivot's 2-mm offsets all within 1 cm of the
    # axis line): the Haar draws' share against the estimate's, and the axis's other bounds.
    near = w[sw <= math.radians(20.0)].sum() / w.sum()
    assert abs(m.mass_near_axis(20.0, 0.01) - near) < 0.02, (m.mass_near_axis(20.0, 0.01), near)
    assert m.mass_near_axis(20.0, 0.01, direction=T_REF[:3, :3] @ AXIS) == m.mass_near_axis(20.0, 0.01)
    assert abs(m.mass_near_axis(180.0, np.inf) - 1.0) < 1e-9 and m.mass_near_axis(20.0, 1e-4) < 0.01


@pytest.mark.slow
def test_stated_error_is_the_observed_error():
    exact = None
    errs, stated = [], []
    for seed in range(6):
        m = axis_marginal(_target, T_REF, AXIS, pivot=PIVOT, max_swing_deg=MAX_SWING, bin_deg=10.0,
                          draws=20_000, pilot_draws=10_000, rng=seed)
        exact = _quadrature(m.edges_deg) if exact is None else exact
        errs.append(0.5 * np.abs(m.mass - exact).sum())
        stated.append(m.tv_error)
    ratio = np.mean(errs) / np.mean(stated)
    assert 0.5 < ratio < 2.0, (errs, stated)


def test_compare_and_histogram_of_a_distribution():
    m = axis_marginal(_target, T_REF, AXIS, pivot=PIVOT, max_swing_deg=MAX_SWING, bin_deg=10.0,
                      draws=50_000, rng=2)
    # Draws of the target itself (the reference's own weighted draws are not exposed): rotations
    # about the axis at the bin centres, weighted by the bin masses, score TV 0; a quarter of the
    # circle only scores what it leaves out; a flipped set (axis reversed) lies outside the region.
    centres = np.radians(0.5 * (m.edges_deg[1:] + m.edges_deg[:-1]))
    R = T_REF[:3, :3] @ Rotation.from_rotvec(centres[:, None] * AXIS).as_matrix()
    t = np.tile(T_REF[:3, 3], (len(R), 1))
    assert m.compare(PoseDistribution(R, t, m.mass))[0] < 1e-12
    quarter = np.abs(centres) < math.pi / 4
    tv, outside = m.compare(PoseDistribution(R[quarter], t[quarter], m.mass[quarter] / m.mass[quarter].sum()))
    assert abs(tv - (1.0 - m.mass[quarter].sum())) < 1e-9 and outside == 0.0
    flip = Rotation.from_rotvec(math.pi * np.cross(AXIS, [1.0, 0, 0]) / np.linalg.norm(np.cross(AXIS, [1.0, 0, 0])))
    R2 = np.concatenate([R, R @ flip.as_matrix()])
    h, outside = m.histogram(R2, np.concatenate([m.mass, m.mass]))
    assert abs(outside - 0.5) < 1e-9 and np.allclose(h, m.mass)


@settings(max_examples=60, deadline=None)
@given(theta=st.floats(-3.1, 3.1), sx=st.floats(-1.0, 1.0), sy=st.floats(-1.0, 1.0),
       scale=st.sampled_from([1e-9, 1e-4, 1.0]))
def test_twist_and_swing_of_the_parametrisation(theta, sx, sy, scale):
    # R = R_ref exp(s) exp(theta a), s orthogonal to a: axis_angles gives theta, swing_angles |s|,
    # near the identity too.
    u = np.cross(AXIS, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    s = scale * (sx * u + sy * np.cross(AXIS, u))
    R = T_REF[:3, :3] @ (Rotation.from_rotvec(s) * Rotation.from_rotvec(theta * AXIS)).as_matrix()
    assert abs(axis_angles(R[None], AXIS, T_REF)[0] - theta) < 1e-7
    assert abs(swing_angles(R[None], AXIS, T_REF)[0] - np.linalg.norm(s)) < 1e-6


@pytest.mark.parametrize(("kw", "match"), [
    ({"axis": [0.0, 0.0, 0.0]}, "axis"),
    ({"axis": [1.0, 0.0]}, "shape"),
    ({"temperature": 0.0}, "temperature"),
    ({"bin_deg": 7.0}, "bin_deg"),
    ({"max_swing_deg": 180.0}, "max_swing_deg"),
    ({"draws": 0}, "draws"),
    ({"pilot_rounds": -1}, "pilot_rounds"),
    ({"pivot": [0.0, 0.0]}, "pivot"),
    ({"initial_scale": (0.0, 0.01)}, "initial_scale"),
])
def test_bad_input(kw, match):
    args = {"axis": AXIS, **kw}
    with pytest.raises(ValueError, match=match):
        axis_marginal(_target, T_REF, args.pop("axis"), **args)


def test_target_of_wrong_shape_or_nowhere():
    with pytest.raises(ValueError, match="log_target"):
        axis_marginal(lambda T: np.zeros((len(T), 2)), T_REF, AXIS, draws=100, pilot_rounds=0)
    with pytest.raises(RuntimeError, match="zero target density"):
        axis_marginal(lambda T: np.full(len(T), -np.inf), T_REF, AXIS, draws=100, pilot_rounds=0)
