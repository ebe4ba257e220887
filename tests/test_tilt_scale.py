"""PoseDistribution.with_tilt_scale: the tilt of a body of revolution's axis across its basin's
mean axis is scaled; the point on the axis, the spin about it and the weights are kept; an
upright and an upside-down basin are scaled each about its own mean."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from certpose.sampling import PoseDistribution

AXIS = np.array([0.0, 0.0, 1.0])
CENTRE = np.array([0.01, -0.02, 0.03])


def basin(rng: np.random.Generator, n: int, tilt_deg: float, flip: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Rotations whose axis tilts about ``tilt_deg`` per direction from camera z (or -z) and which
    spin freely about it, and translations about 0.5 m away."""
    spin = Rotation.from_rotvec(np.outer(rng.uniform(-np.pi, np.pi, n), AXIS))
    tilt = Rotation.from_rotvec(np.c_[rng.normal(scale=math.radians(tilt_deg), size=(n, 2)), np.zeros(n)])
    R = tilt * spin
    if flip:
        R = Rotation.from_rotvec([math.pi, 0.0, 0.0]) * R
    t = rng.normal(scale=0.01, size=(n, 3)) + [0.0, 0.0, 0.5]
    return R.as_matrix(), t


def spin_of(R: np.ndarray) -> np.ndarray:
    """Angle about the axis, read as the swing-twist twist of each rotation (radians)."""
    q = Rotation.from_matrix(R).as_quat()  # x, y, z, w
    return np.angle(np.exp(2j * np.arctan2(q[:, 2], q[:, 3])))


def angles_deg(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angles between the rows of ``u`` and ``v`` (degrees; atan2, exact near 0)."""
    v = np.broadcast_to(v, u.shape)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(u, v), axis=1), np.einsum("ij,ij->i", u, v)))


def two_basins(seed: int = 0) -> PoseDistribution:
    rng = np.random.default_rng(seed)
    Ra, ta = basin(rng, 600, 3.0)
    Rb, tb = basin(rng, 400, 3.0, flip=True)
    w = rng.uniform(0.5, 1.5, 1000)
    return PoseDistribution(np.concatenate([Ra, Rb]), np.concatenate([ta, tb]), w / w.sum())


@settings(max_examples=40, deadline=None)
@given(scale=st.floats(0.0, 1.5), seed=st.integers(0, 10_000))
def test_tilt_from_the_basin_mean_is_scaled_and_the_axis_point_kept(scale: float, seed: int) -> None:
    d = two_basins(seed)
    e = d.with_tilt_scale(scale, axis=AXIS, centre=CENTRE)
    np.testing.assert_array_equal(e.weights, d.weights)
    # The point on the axis stays where it was.
    np.testing.assert_allclose(e.rotations @ CENTRE + e.translations, d.rotations @ CENTRE + d.translations,
                               atol=1e-12)
    for half, sign in ((slice(0, 600), 1.0), (slice(600, 1000), -1.0)):
        a0 = d.rotations[half] @ AXIS
        a1 = e.rotations[half] @ AXIS
        m = d.weights[half] @ a0
        m /= np.linalg.norm(m)
        assert m[2] * sign > 0.99
        np.testing.assert_allclose(angles_deg(a1, m), scale * angles_deg(a0, m), atol=1e-6)
        # Moved towards (or away from) the mean in the plane of the axis and the mean.
        np.testing.assert_allclose(np.einsum("ij,ij->i", np.cross(a0, m), a1), 0.0, atol=1e-9)


def test_near_identity_scale_changes_nothing_much_and_scale_one_nothing() -> None:
    d = two_basins(1)
    same = d.with_tilt_scale(1.0, axis=AXIS, centre=CENTRE)
    np.testing.assert_array_equal(same.rotations, d.rotations)
    near = d.with_tilt_scale(1.0 - 1e-9, axis=AXIS, centre=CENTRE)
    np.testing.assert_allclose(near.rotations, d.rotations, atol=1e-9)


def test_spin_about_the_axis_is_kept_and_zero_scale_puts_every_axis_on_its_mean() -> None:
    rng = np.random.default_rng(2)
    R, t = basin(rng, 2000, 4.0)
    d = PoseDistribution(R, t, np.full(2000, 1 / 2000))
    e = d.with_tilt_scale(0.0, axis=AXIS, centre=CENTRE)
    a = e.rotations @ AXIS
    m = d.weights @ (d.rotations @ AXIS)
    m /= np.linalg.norm(m)
    assert angles_deg(a, m).max() < 1e-6
    # The least rotation moves the axis only: the spin of each particle changes by no more than
    # the swing's own second-order twist (tilts of a few degrees: well under a degree).
    dspin = np.degrees(np.angle(np.exp(1j * (spin_of(e.rotations) - spin_of(d.rotations)))))
    assert np.abs(dspin).max() < 1.0, np.abs(dspin).max()
    # A uniform spin stays uniform (no drift towards one turn).
    hist = np.histogram(spin_of(e.rotations), bins=8, range=(-np.pi, np.pi))[0]
    assert hist.min() > 150, hist


def test_a_wider_tilt_makes_the_axis_ok_mass_smaller_and_scaling_it_back_restores_it() -> None:
    rng = np.random.default_rng(3)
    R, t = basin(rng, 4000, 4.0)
    d = PoseDistribution(R, t, np.full(4000, 1 / 4000))

    def within5(x: PoseDistribution) -> float:
        return float(x.weights[angles_deg(x.rotations @ AXIS, AXIS) <= 5.0].sum())

    half = d.with_tilt_scale(0.5, axis=AXIS, centre=CENTRE)
    # A 2-D Gaussian tilt of 4 deg per direction holds 1 - exp(-25 / 32) = 0.54 within 5 deg;
    # of 2 deg, 1 - exp(-25 / 8) = 0.96.
    assert abs(within5(d) - (1 - math.exp(-25 / 32))) < 0.03
    assert abs(within5(half) - (1 - math.exp(-25 / 8))) < 0.02


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"scale": -0.1}, "scale"), ({"scale": float("nan")}, "scale"),
    ({"scale": 0.5, "axis": [0.0, 0.0, 0.0]}, "axis"), ({"scale": 0.5, "axis": [1.0, 0.0]}, "axis"),
    ({"scale": 0.5, "basin_deg": 0.0}, "basin_deg"), ({"scale": 0.5, "basin_deg": 95.0}, "basin_deg"),
    ({"scale": 0.5, "centre": [0.0, float("nan"), 0.0]}, "centre"),
])
def test_bad_arguments_are_refused_by_name(kwargs: dict, match: str) -> None:
    d = two_basins(4)
    kwargs = {"axis": AXIS, **kwargs}
    with pytest.raises(ValueError, match=match):
        d.with_tilt_scale(kwargs.pop("scale"), **kwargs)
