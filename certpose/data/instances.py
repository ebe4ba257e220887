"""Registration instances with ground truth: the TEASER++/QUASAR benchmark protocol.

``N`` points sampled from a shape scaled into the unit cube, a random rotation, a translation
uniform in the unit ball, isotropic Gaussian noise ``sigma`` on the inliers, outliers replacing
target points with points drawn uniformly in a ball of radius 5, noise bound
``beta = 5.54 sigma``. The one generator of the benchmark, ``certpose register --demo`` and the
tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from solvers.validation import check_points, resolve_rng

__all__ = ["BenchInstance", "make_instance", "NOISE_BOUND_FACTOR", "OUTLIER_RADIUS"]

NOISE_BOUND_FACTOR = 5.54
"""``beta / sigma``: the noise bound that holds an inlier's residual with probability ~0.99997."""
OUTLIER_RADIUS = 5.0
"""Radius of the ball the outliers are drawn in (unit-cube shapes)."""


@dataclass(frozen=True)
class BenchInstance:
    """One registration instance with its ground truth.

    Attributes
    ----------
    source, target : (N, 3) ndarray
        Corresponding points (dimensionless, the shape's unit cube).
    rotation, translation : (3, 3), (3,) ndarray
        Ground truth: ``target[k] = rotation @ source[k] + translation + noise`` for inliers.
    outliers : (N,) ndarray of bool
        Which target points were replaced by outliers.
    noise_bound : float
        ``beta = 5.54 sigma``.
    """

    source: NDArray[np.float64]
    target: NDArray[np.float64]
    rotation: NDArray[np.float64]
    translation: NDArray[np.float64]
    outliers: NDArray[np.bool_]
    noise_bound: float


def _uniform_in_ball(rng: np.random.Generator, count: int, radius: float) -> NDArray[np.float64]:
    d = rng.normal(size=(count, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * (radius * rng.uniform(size=(count, 1)) ** (1.0 / 3.0))


def make_instance(
    shape: NDArray[np.float64],
    n: int,
    outlier_ratio: float,
    *,
    noise: float,
    rng: np.random.Generator | int | None = None,
) -> BenchInstance:
    """Draw one instance of the TEASER++/QUASAR benchmark protocol.

    Parameters
    ----------
    shape : (M, 3) ndarray
        Points of the shape, already scaled into the unit cube.
    n : int
        Number of correspondences; drawn without replacement when ``n <= M``.
    outlier_ratio : float
        Fraction in ``[0, 1)`` of target points replaced by outliers (``floor(ratio * n)``).
    noise : float
        Standard deviation of the isotropic Gaussian noise on inlier targets.
    rng : numpy.random.Generator, int or None

    Returns
    -------
    BenchInstance
    """
    shape = check_points(shape, "shape", min_points=3)
    if n < 3:
        raise ValueError(f"`n` must be >= 3, got {n}.")
    if not 0.0 <= outlier_ratio < 1.0:
        raise ValueError(f"`outlier_ratio` must be in [0, 1), got {outlier_ratio}.")
    gen = resolve_rng(rng)
    idx = gen.choice(shape.shape[0], size=n, replace=n > shape.shape[0])
    source = shape[idx]
    R = Rotation.random(random_state=gen).as_matrix()
    t = _uniform_in_ball(gen, 1, 1.0)[0]
    target = source @ R.T + t + noise * gen.normal(size=(n, 3))
    n_out = int(math.floor(outlier_ratio * n + 1e-9))
    outliers = np.zeros(n, dtype=bool)
    outliers[gen.choice(n, size=n_out, replace=False)] = True
    target[outliers] = _uniform_in_ball(gen, n_out, OUTLIER_RADIUS)
    return BenchInstance(source, target, R, t, outliers, NOISE_BOUND_FACTOR * noise)
