"""Shared test fixtures: paths to ../shared/data and instance generators."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

from certpose.data import instances

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


def mug_on_0000(frame: str = "000001"):
    """The mug on YCB-Video 0000/``frame`` for the hidden-handle arc tests: the pipeline's set-up,
    its ground truth ``T_camera_object``, the body axis' offset in the model frame and
    ``bench_arc.turned_pose`` (examples/benchmarks/bench_arc.py)."""
    import sys

    from certpose.estimation.pipeline import ycbv_setup

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "benchmarks"))
    from bench_arc import body_axis_offset, turned_pose

    s = ycbv_setup(require_data("ycbv"), f"0000/{frame}", "025_mug")
    return s, s.frame.poses["025_mug"], body_axis_offset(s.model_points), turned_pose


def mug_body(obj):  # noqa: ANN001, ANN201
    """The mug's model without its handle (points with x < 45 mm in the model frame)."""
    return obj.select(np.flatnonzero(obj.points[:, 0] < 0.045))


def refined_turn(lik, G: np.ndarray, C: np.ndarray, turned_pose, angle: float) -> np.ndarray:  # noqa: ANN001
    """``G`` turned by ``angle`` deg about the body axis through ``C``, the other five degrees of
    freedom refined on ``lik`` (Powell, the settings of examples/benchmarks/bench_arc.py): the pose (4, 4)."""
    from scipy.optimize import minimize

    scale = np.array([0.05, 0.05, 0.005, 0.005, 0.005])
    x = minimize(lambda u: -float(lik(turned_pose(G, C, angle, u * scale))), np.zeros(5), method="Powell",
                 options={"xtol": 1e-2, "ftol": 1e-4, "maxfev": 400}).x
    return turned_pose(G, C, angle, x * scale)


def strict_json(text: str) -> object:
    """Parse JSON as the standard says: ``NaN`` and ``Infinity`` (which Python writes and reads by
    default) are errors."""

    def reject(token: str) -> object:
        raise ValueError(f"invalid JSON constant {token!r}")

    return json.loads(text, parse_constant=reject)


def box_surface(rng: np.random.Generator, size: np.ndarray, per_face: int) -> np.ndarray:
    """Points uniform on each face of an axis-aligned box of ``size`` (3,) centred at 0, shape
    ``(6 * per_face, 3)``."""
    pts = []
    for axis in range(3):
        for sign in (-0.5, 0.5):
            uv = rng.uniform(-0.5, 0.5, size=(per_face, 3)) * size
            uv[:, axis] = sign * size[axis]
            pts.append(uv)
    return np.concatenate(pts)


def make_instance(
    rng: np.random.Generator,
    n: int,
    outlier_ratio: float,
    *,
    sigma: float = 0.01,
    points: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`certpose.data.instances.make_instance` on ``points`` (default: ``n`` points uniform
    in the unit cube) as a tuple ``(source, target, R, t, is_inlier)``."""
    shape = rng.uniform(-0.5, 0.5, size=(n, 3)) if points is None else points
    inst = instances.make_instance(shape, n, outlier_ratio, noise=sigma, rng=rng)
    return inst.source, inst.target, inst.rotation, inst.translation, ~inst.outliers


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(autouse=True, scope="session")
def _object_cache_in_tmp(tmp_path_factory: pytest.TempPathFactory):
    """``certpose pose`` keeps object models in $CERTPOSE_CACHE_DIR: the tests' go to a temporary
    directory, not the user's cache (each test session builds them afresh)."""
    old = os.environ.get("CERTPOSE_CACHE_DIR")
    os.environ["CERTPOSE_CACHE_DIR"] = str(tmp_path_factory.mktemp("certpose-cache"))
    yield
    if old is None:
        os.environ.pop("CERTPOSE_CACHE_DIR", None)
    else:
        os.environ["CERTPOSE_CACHE_DIR"] = old


def observed_plane(shape: tuple[int, int, int]):  # noqa: ANN201
    """A hand-built scene for the blur tests: an observed plane (``k = 0``, 5-mm voxels) of one
    descriptor ``[1, 0]`` and classifier positives (log 0.9) under free space; returns the
    scene, its classification and a model of three points at one place with that descriptor."""
    import math

    from certpose.geometry.objects import ObjectModel
    from certpose.model.classifier import ClassifierStatus, ObjectClassification
    from certpose.model.grid import EMPTY, OCCUPIED
    from certpose.model.scene import SceneField

    state = np.full(shape, EMPTY, dtype=np.int8)
    state[:, :, 0] = OCCUPIED
    desc = np.zeros((*shape, 2))
    desc[:, :, 0, 0] = 1.0
    scene = SceneField(0.005, np.zeros(3), shape, desc, state)
    cls = ObjectClassification(np.where(state == OCCUPIED, math.log(0.9), -5.0), state == OCCUPIED,
                               -5.0, "t", ClassifierStatus.OK, "")
    return scene, cls, ObjectModel(np.zeros((3, 3)), np.tile([1.0, 0.0], (3, 1)))
