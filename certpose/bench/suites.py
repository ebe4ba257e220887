"""Benchmark suites: which instances a run holds, and how a worker makes one from its spec.

A run is a list of :class:`InstanceSpec`: small, picklable descriptions (a seed and a grid
place, a file path, a data folder) from which any process draws or loads the instance itself
(:func:`load_instance`), so Dask workers receive specs, never arrays. Suites (:data:`SUITES`):

``synthetic``, ``bunny``
    The TEASER++/QUASAR protocol (:mod:`certpose.data.instances`) on the built-in shape
    or the Stanford bunny (``DATA/bunny/bun_zipper_res3.ply``), over the grid of N, outlier
    ratios and trials. Success: rotation error < 5 deg and translation error < 0.05.
``3dmatch``
    The real scan pair of ``DATA/3dmatch`` with FPFH putative correspondences and its given
    ground truth (:mod:`certpose.data.threedmatch`). Success: < 5 deg and < 0.1 m.
``eq2``
    Eq. (2) problems of the pose model: ``trials`` synthetic mug scenes (seeds) and, when
    ``DATA/ycbv`` is present, the YCB-Video frames of :data:`EQ2_YCBV_FRAMES`. Success against
    the object's ground truth: < 10 deg (the symmetry axis for symmetric objects) and < 2 cm.
``problems``
    Every ``*.npz`` problem file (:mod:`certpose.io.problems`) under a folder; tolerances from
    the file's metadata (``rotation_tol_deg``, ``translation_tol``; default 5 deg, 0.05).
    Without ground truth, success is the solver's own verdict.
"""

from __future__ import annotations

import functools
import os
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "SUITES",
    "EQ2_YCBV_FRAMES",
    "InstanceSpec",
    "Instance",
    "default_data_dir",
    "protocol_specs",
    "problem_specs",
    "threedmatch_specs",
    "eq2_specs",
    "load_instance",
    "instance_seed",
]

SUITES = ("synthetic", "bunny", "3dmatch", "eq2")
"""Named suites of ``certpose bench --suite``."""

BUNNY_FILE = ("bunny", "bun_zipper_res3.ply")
EQ2_YCBV_FRAMES = (
    ("0000/000001", "025_mug"),
    ("0002/000001", "006_mustard_bottle"),
    ("0049/000001", "004_sugar_box"),
    ("0050/000001", "035_power_drill"),
)
"""YCB-Video (frame, object) pairs of the ``eq2`` suite."""

ROTATION_TOL_DEG = 5.0
TRANSLATION_TOL = 0.05
THREEDMATCH_TRANSLATION_TOL = 0.1


@dataclass(frozen=True)
class InstanceSpec:
    """What a process needs to make one instance.

    Attributes
    ----------
    suite : str
        The rows' ``suite`` column.
    instance : str
        Id of the instance within its suite (the rows' ``instance`` column).
    seed : int
        The instance's seed (protocol: it draws the instance; others: a hash of the id).
    trial : int
        Index within its grid cell (0 outside the protocol).
    kind : {"protocol", "file", "3dmatch", "eq2-synthetic", "eq2-ycbv"}
    args : tuple
        Kind-specific: ``(n, ratio)``; ``(path,)``; ``(data_dir,)``; ``()``;
        ``(ycbv_dir, frame, object)``.
    """

    suite: str
    instance: str
    seed: int
    trial: int
    kind: str
    args: tuple[Any, ...] = ()


@dataclass(frozen=True, eq=False)
class Instance:
    """One benchmark instance, with its ground truth when known.

    Attributes
    ----------
    source, target : (N, 3) ndarray
    weights : (N,) ndarray or None
        ``None``: all 1.
    noise_bound : float or (N,) ndarray
    rotation, translation : (3, 3), (3,) ndarray or None
        Ground truth ``T_target_source``.
    n : int
    outlier_ratio : float
        Protocol: the grid's ratio; otherwise the fraction of ground-truth residuals above their
        bound (NaN without ground truth).
    rotation_tol_deg, translation_tol : float
        Success thresholds.
    symmetry_axis : (3,) ndarray or None
        Source-frame axis: the rotation error is then the axis' angle error.
    """

    source: NDArray[np.float64]
    target: NDArray[np.float64]
    weights: NDArray[np.float64] | None
    noise_bound: float | NDArray[np.float64]
    rotation: NDArray[np.float64] | None
    translation: NDArray[np.float64] | None
    n: int
    outlier_ratio: float
    rotation_tol_deg: float = ROTATION_TOL_DEG
    translation_tol: float = TRANSLATION_TOL
    symmetry_axis: NDArray[np.float64] | None = None

    @property
    def scalar_noise_bound(self) -> float:
        """One bound for peers that take one: the largest."""
        return float(np.max(self.noise_bound))

    @functools.cached_property
    def problem(self) -> Any:
        """The weighted TLS problem (for the cost of any solver's pose)."""
        from solvers import WeightedTLSProblem

        return WeightedTLSProblem(self.source, self.target, noise_bound=self.noise_bound,
                                  weights=self.weights)


def default_data_dir() -> Path:
    """``$CERTPOSE_DATA``, else ``../shared/data`` from the working folder, else beside the
    repository (``<repo>/../shared/data``)."""
    env = os.environ.get("CERTPOSE_DATA")
    if env:
        return Path(env)
    here = Path("../shared/data")
    if here.is_dir():
        return here
    return Path(__file__).resolve().parents[3] / "shared" / "data"


def instance_seed(seed: int, n: int, ratio: float, trial: int) -> int:
    """Seed of one protocol instance, from the run's seed and the instance's place in the grid.

    Independent of the order instances are drawn in, so any worker can draw any instance, and
    a resumed run draws the same ones. Non-negative and below ``2**63`` (a pandas ``int64``).
    """
    ss = np.random.SeedSequence([int(seed), int(n), round(float(ratio) * 1e9), int(trial)])
    return int(ss.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


def _id_seed(text: str) -> int:
    return zlib.crc32(text.encode("utf-8"))


def protocol_specs(
    suite: str, n_values: tuple[int, ...], ratios: tuple[float, ...], trials: int, seed: int
) -> Iterator[InstanceSpec]:
    """The protocol's grid: one spec per (N, ratio, trial), drawn one at a time."""
    for n in n_values:
        for ratio in ratios:
            for trial in range(trials):
                yield InstanceSpec(suite, f"N{n}-r{ratio:g}-t{trial}-s{seed}",
                                   instance_seed(seed, n, ratio, trial), trial, "protocol",
                                   (n, ratio))


def problem_specs(folder: str | os.PathLike[str], suite: str | None = None, *,
                  check: bool = True) -> list[InstanceSpec]:
    """One spec per ``*.npz`` file under ``folder`` (recursively, sorted); the id is the path
    relative to ``folder``. With ``check``, every file is read once here (one at a time, not
    kept) so that a malformed one stops the run before any work.

    Raises
    ------
    FileNotFoundError, NotADirectoryError
        ``folder`` is missing or not a folder.
    ValueError
        It holds no ``.npz`` file; a file is malformed (``check``).
    """
    root = Path(folder)
    if not root.exists():
        raise FileNotFoundError(f"--problems folder '{root}' does not exist.")
    if not root.is_dir():
        raise NotADirectoryError(f"--problems '{root}' is not a folder.")
    files = sorted(root.rglob("*.npz"))
    if not files:
        raise ValueError(f"--problems folder '{root}' holds no .npz problem file.")
    name = suite or root.resolve().name
    out = []
    for f in files:
        if check:
            from certpose.io.problems import load_problem

            load_problem(f)
        rel = f.relative_to(root).as_posix()
        out.append(InstanceSpec(name, rel, _id_seed(rel), 0, "file", (str(f.resolve()),)))
    return out


def threedmatch_specs(data_dir: str | os.PathLike[str]) -> list[InstanceSpec]:
    """The 3DMatch pair of ``data_dir/3dmatch`` (one instance).

    Raises
    ------
    FileNotFoundError
        The pair's files are missing.
    """
    folder = Path(data_dir) / "3dmatch"
    missing = [n for n in ("src.npy", "ref.npy", "gt.npy") if not (folder / n).is_file()]
    if missing:
        raise FileNotFoundError(f"the 3dmatch suite needs {', '.join(missing)} in '{folder}' "
                                "(give the data folder with --data DIR).")
    return [InstanceSpec("3dmatch", "pair", _id_seed("3dmatch/pair"), 0, "3dmatch",
                         (str(folder.resolve()),))]


def eq2_specs(trials: int, seed: int, data_dir: str | os.PathLike[str] | None) -> list[InstanceSpec]:
    """``trials`` synthetic mug scenes and, when ``data_dir/ycbv`` exists, the YCB-Video frames
    of :data:`EQ2_YCBV_FRAMES`."""
    specs = [InstanceSpec("eq2", f"synthetic-s{s}", s, t, "eq2-synthetic")
             for t, s in enumerate(range(seed, seed + trials))]
    ycbv = None if data_dir is None else Path(data_dir) / "ycbv"
    if ycbv is not None and ycbv.is_dir():
        for frame, obj in EQ2_YCBV_FRAMES:
            if (ycbv / frame.split("/")[0]).is_dir():
                iid = f"ycbv-{frame.replace('/', '-')}-{obj}"
                specs.append(InstanceSpec("eq2", iid, _id_seed(iid), 0, "eq2-ycbv",
                                          (str(ycbv.resolve()), frame, obj)))
    return specs


# --------------------------------------------------------------------------- making instances


def load_instance(spec: InstanceSpec, shapes: dict[str, NDArray[np.float64]], noise: float
                  ) -> Instance:
    """Make the instance of ``spec`` in this process (protocol shapes come from ``shapes``,
    keyed by suite)."""
    if spec.kind == "protocol":
        from certpose.data.instances import make_instance

        n, ratio = spec.args
        inst = make_instance(shapes[spec.suite], n, ratio, noise=noise, rng=spec.seed)
        return Instance(inst.source, inst.target, None, inst.noise_bound, inst.rotation,
                        inst.translation, n, ratio)
    if spec.kind == "file":
        from certpose.io.problems import load_problem

        return _from_problem(load_problem(spec.args[0]).__dict__)
    if spec.kind == "3dmatch":
        return _threedmatch(spec.args[0])
    if spec.kind == "eq2-synthetic":
        return _eq2_synthetic(spec.seed)
    if spec.kind == "eq2-ycbv":
        from certpose.estimation.pipeline import build_eq2_ycbv

        return _from_problem(build_eq2_ycbv(*spec.args, rng=spec.seed))
    raise ValueError(f"unknown instance kind {spec.kind!r}.")


def _from_problem(d: dict[str, Any], *, rotation_tol_deg: float | None = None,
                  translation_tol: float | None = None) -> Instance:
    """An :class:`Instance` from a problem file's fields (or :func:`save_problem`'s keywords)."""
    meta = d.get("metadata") or {}
    # Copies: some peers (Open3D) need writable arrays, and problems hold read-only ones.
    src = np.array(d["source"], dtype=np.float64)
    dst = np.array(d["target"], dtype=np.float64)
    beta = d["noise_bound"]
    beta = float(beta) if np.ndim(beta) == 0 else np.asarray(beta, dtype=np.float64)
    T = d.get("T_target_source")
    R = t = None
    ratio = float("nan")
    if T is not None:
        T = np.asarray(T, dtype=np.float64)
        R, t = T[:3, :3], T[:3, 3]
        r = np.linalg.norm(dst - src @ R.T - t, axis=1)
        ratio = float(np.mean(r > np.asarray(beta)))
    axis = meta.get("symmetry_axis")
    return Instance(
        src, dst, np.array(d["weights"], dtype=np.float64), beta, R, t, int(src.shape[0]),
        ratio,
        float(rotation_tol_deg or meta.get("rotation_tol_deg", ROTATION_TOL_DEG)),
        float(translation_tol or meta.get("translation_tol", TRANSLATION_TOL)),
        None if axis is None else np.asarray(axis, dtype=np.float64),
    )


@functools.lru_cache(maxsize=4)
def _eq2_synthetic(seed: int) -> Instance:
    from certpose.estimation.pipeline import build_eq2_demo

    return _from_problem(build_eq2_demo(rng=seed))


@functools.lru_cache(maxsize=2)
def _threedmatch(folder: str) -> Instance:
    """The pair's FPFH correspondences (cached per process: they take seconds to compute)."""
    from certpose.data.threedmatch import NOISE_BOUND, threedmatch_correspondences

    c = threedmatch_correspondences(Path(folder))
    d = {"source": c.source, "target": c.target, "weights": np.ones(c.n),
         "noise_bound": NOISE_BOUND, "T_target_source": c.T_target_source}
    return _from_problem(d, translation_tol=THREEDMATCH_TRANSLATION_TOL)
