"""Shared test fixtures: paths to ../shared/data and instance generators."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings
from scipy.spatial.transform import Rotation

# No per-example deadline: the first example of a property may load a compiled numba kernel, and
# the machine is shared; timing belongs in benchmarks, not in tests.
settings.register_profile("certpose", deadline=None)
settings.load_profile("certpose")

DATA_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def require_data(*parts: str) -> Path:
    """Path under ../shared/data; skip (or fail under CI) when it is missing."""
    path = DATA_DIR.joinpath(*parts)
    if not path.exists():
        msg = f"test data {path} is missing (expected ../shared/data beside the repository)"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    return path


def make_instance(
    rng: np.random.Generator,
    n: int,
    outlier_ratio: float,
    *,
    sigma: float = 0.01,
    points: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The NOTES.md section 3 protocol: returns (source, target, R, t, is_inlier)."""
    if points is None:
        src = rng.uniform(-0.5, 0.5, size=(n, 3))
    else:
        src = points[rng.choice(points.shape[0], size=n, replace=False)]
    R = Rotation.random(random_state=rng).as_matrix()
    t = rng.normal(size=3)
    t *= rng.uniform() ** (1 / 3) / np.linalg.norm(t)
    dst = src @ R.T + t + rng.normal(0.0, sigma, size=(n, 3))
    n_out = int(round(outlier_ratio * n))
    out = rng.choice(n, size=n_out, replace=False)
    d = rng.normal(size=(n_out, 3))
    d *= 5.0 * rng.uniform(size=(n_out, 1)) ** (1 / 3) / np.linalg.norm(d, axis=1, keepdims=True)
    dst[out] = d
    inl = np.ones(n, dtype=bool)
    inl[out] = False
    return src, dst, R, t, inl


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
