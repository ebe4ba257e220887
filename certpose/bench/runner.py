"""Registration benchmark: certpose's solvers and peers side by side on the same instances.

Instances come from suites (:mod:`certpose.bench.suites`): the TEASER++/QUASAR protocol
on the built-in shape or the Stanford bunny (``N`` points in the unit cube, a random pose,
Gaussian noise ``sigma`` on the inliers, outliers uniform in a ball of radius 5, noise bound
``beta = 5.54 sigma``; success: rotation error < 5 deg and translation error < 0.05), the real
3DMatch pair with FPFH correspondences, eq. (2) problems of the pose model, and any folder of
problem files.

Every solver sees exactly the same instances. Each instance is made from its spec (a seed and
a grid place, a file path, a data folder), in whichever process runs it: in this process
(``workers=0``) or on Dask workers (a ``LocalCluster`` or a running scheduler), which receive
specs, not arrays. Rows, one per (instance, solver) and keyed by ``(suite, instance, solver)``,
are streamed to ``trials.csv`` as they finish (:mod:`certpose.bench.rows`), so an interrupted
run resumes where it stopped; the summary is computed from that file
(:mod:`certpose.bench.report`), so the driver keeps no row in memory. Times are wall-clock
seconds around each call, including the solver's own conversion of the input arrays (building
a factor graph, Open3D point clouds, validating the problem...); for certpose's solvers the
time the result reports itself (``solve_time``) is recorded too (``reported_time_ms``). Each
solver is run once on a throw-away instance first, so JIT compilation and lazy imports are
not timed. Within a batch (a Dask task, or the whole run in process), the instances are made
first and each solver then runs on all of them in turn (not interleaved with the others, which
slowed every solver down). Every solver runs on one thread: Open3D's parallel loops are
limited to one (its RANSAC result depends on the thread count; rows must not depend on where
they ran). ``cost`` is the weighted TLS cost of the returned pose on the
instance's problem, for every solver.

Solvers (:data:`SOLVERS`):

``gnc``
    ``certpose.register`` with automatic max-clique pruning (the front-end).
``gnc-only``
    ``certpose.register(..., prune="never")``: GNC-TLS alone.
``gnc+certify``
    ``certpose.register(..., certify=True)``: the front-end's pose with a certificate of the
    full problem (``scope="auto"``), or, when the full problem's bound gives up (real scans,
    eq. (2)), of the rotation subproblem over the max clique (its certified optimum returned,
    ``prefer="certificate"``); the rows record which problem each certificate bounds.
``gnc+cert-pruned``, ``gnc+cert-rotation``
    The same with ``scope="pruned"`` (the problem left after max-clique pruning) and
    ``scope="rotation"`` (the rotation subproblem over translation-invariant measurements,
    what TEASER++ certifies).
``sdp``
    ``certpose.register(..., solver="sdp")``: the SDP relaxation's rounded pose.
``gtsam-gnc``
    GTSAM's ``GncLMOptimizer`` with the TLS loss, one ``Pose3`` and one
    ``KnownLandmarkFactorPose3`` per correspondence (noise sigma ``beta``, inlier threshold the
    same TLS truncation as certpose), initialised at the identity.
``o3d-ransac``
    Open3D ``registration_ransac_based_on_correspondence`` (inlier distance ``beta``,
    3-point samples, edge-length checker, at most 100000 iterations, confidence 0.999).
``o3d-fgr``
    Open3D ``registration_fgr_based_on_correspondence`` (absolute scale, maximum
    correspondence distance ``beta``).
``teaser++``
    TEASER++'s Python binding (``teaserpp_python``, built from source: it has no wheel) with
    GNC-TLS rotation estimation, ``cbar2 = 1`` and no scale estimation. Skipped when the
    module cannot be imported.

Peers take one noise bound and no weights: with per-correspondence bounds they get the
largest, and weights are ignored (certpose's solvers use both).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import tempfile
import time
import weakref
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from certpose.bench.report import (
    SCOPE_COLUMNS,
    SUMMARY_COLUMNS,
    format_table,
    plot_report,
    summarize,
    summarize_file,
    write_markdown,
)
from certpose.bench.rows import TRIAL_COLUMNS, bench_extra
from certpose.bench.suites import (
    SUITES,
    Instance,
    InstanceSpec,
    default_data_dir,
    eq2_specs,
    instance_seed,
    load_instance,
    problem_specs,
    protocol_specs,
    threedmatch_specs,
)
from certpose.data.instances import NOISE_BOUND_FACTOR
from certpose.io.output import write_json
from solvers.interrupt import reraise_interrupt
from solvers.lie import rotation_error_deg, translation_error
from solvers.validation import check_points

__all__ = [
    "SOLVERS",
    "DEFAULT_SOLVERS",
    "SUITES",
    "SUMMARY_COLUMNS",
    "SCOPE_COLUMNS",
    "TRIAL_COLUMNS",
    "BenchConfig",
    "BenchReport",
    "run_benchmark",
    "BenchInterrupted",
    "instance_seed",
    "plan_tasks",
    "summarize",
    "format_table",
    "redraw",
]

log = logging.getLogger(__name__)



@dataclass(frozen=True)
class BenchConfig:
    """Suites, grid and solvers of a benchmark run.

    Attributes
    ----------
    n_values : tuple of int
        Numbers of correspondences ``N`` of the protocol suites.
    outlier_ratios : tuple of float
        Fractions of outliers in ``[0, 1)`` of the protocol suites.
    noise : float
        Standard deviation ``sigma`` of the protocol's inlier noise (unit-cube units).
    trials : int
        Instances per ``(N, outlier ratio)`` (and synthetic scenes of the ``eq2`` suite).
    seed : int
        Seed of the instance generator (the same seed gives the same instances).
    solvers : tuple of str
        Names from :data:`SOLVERS`.
    suites : tuple of str
        Names from :data:`certpose.bench.suites.SUITES`; empty: the protocol on the shape given
        to :func:`run_benchmark` (the built-in one by default).
    problems : tuple of str
        Folders of problem files, one suite each (named after the folder).
    data_dir : str or None
        Where ``bunny/``, ``3dmatch/`` and ``ycbv/`` are (default
        :func:`certpose.bench.suites.default_data_dir`).
    """

    n_values: tuple[int, ...] = (100,)
    outlier_ratios: tuple[float, ...] = (0.0, 0.5, 0.8, 0.9, 0.95)
    noise: float = 0.01
    trials: int = 10
    seed: int = 0
    solvers: tuple[str, ...] = ()
    suites: tuple[str, ...] = ()
    problems: tuple[str, ...] = ()
    data_dir: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "n_values", tuple(int(n) for n in self.n_values))
        object.__setattr__(self, "outlier_ratios", tuple(float(r) for r in self.outlier_ratios))
        object.__setattr__(self, "solvers", tuple(self.solvers or DEFAULT_SOLVERS))
        object.__setattr__(self, "suites", tuple(dict.fromkeys(self.suites)))
        object.__setattr__(self, "problems", tuple(str(p) for p in self.problems))
        if not self.n_values or min(self.n_values) < 3:
            raise ValueError(f"`n_values` must be non-empty with every N >= 3, got {self.n_values}.")
        if not self.outlier_ratios or not all(0.0 <= r < 1.0 for r in self.outlier_ratios):
            raise ValueError(
                f"`outlier_ratios` must be non-empty, each in [0, 1), got {self.outlier_ratios}."
            )
        if not (math.isfinite(self.noise) and self.noise > 0):
            raise ValueError(f"`noise` must be a positive finite sigma, got {self.noise}.")
        if self.trials < 1:
            raise ValueError(f"`trials` must be >= 1, got {self.trials}.")
        unknown = [s for s in self.solvers if s not in SOLVERS]
        if unknown:
            raise ValueError(
                f"unknown solver(s) {', '.join(unknown)}; choose from {', '.join(SOLVERS)}."
            )
        if len(set(self.solvers)) != len(self.solvers):
            raise ValueError(f"`solvers` lists a solver twice: {self.solvers}.")
        bad = [s for s in self.suites if s not in SUITES]
        if bad:
            raise ValueError(f"unknown suite(s) {', '.join(bad)}; choose from {', '.join(SUITES)}.")

    @property
    def noise_bound(self) -> float:
        """``beta = 5.54 sigma``."""
        return NOISE_BOUND_FACTOR * self.noise


@dataclass(frozen=True)
class BenchReport:
    """Outcome of :func:`run_benchmark`: the summary, computed from the row file.

    Attributes
    ----------
    config : BenchConfig
    shape : str
        Where the protocol's points came from (a file or ``"synthetic"``).
    rows_path : Path
        The row file (``trials.csv``); read it with pandas, or with :attr:`trials`.
    summary : list of dict
        One record per suite, solver, ``N`` and outlier ratio (keys :data:`SUMMARY_COLUMNS`).
    scopes : list of dict
        One record per solver, certificate problem and outlier ratio (keys
        :data:`SCOPE_COLUMNS`): certified fraction and gaps.
    skipped : dict
        Solvers that could not run, with the reason.
    run : dict
        How this run went: ``wall_seconds`` (the whole call, cluster start included),
        ``rows_written``, ``workers``, ``driver_cpu_seconds`` (this process's CPU time, all its
        threads: with Dask, the scheduler's and the row writing) and ``driver_peak_rss_mb``
        (this process's peak resident memory, which the streamed rows keep flat as the number
        of instances grows).
    """

    config: BenchConfig
    shape: str
    rows_path: Path
    summary: list[dict[str, Any]]
    scopes: list[dict[str, Any]] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)
    run: dict[str, Any] = field(default_factory=dict)

    @property
    def trials(self) -> list[dict[str, Any]]:
        """Every row of the row file, with their types (loaded on each access)."""
        from certpose.bench.rows import read_rows

        return read_rows(self.rows_path, TRIAL_COLUMNS)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (NaN becomes ``None``); the rows stay in ``trials.csv``."""
        return _json_clean(
            {
                "config": asdict(self.config),
                "noise_bound": self.config.noise_bound,
                "shape": self.shape,
                "rows": str(self.rows_path),
                "success_criterion": {
                    "rotation_error_deg_below": 5.0,
                    "translation_error_below": 0.05,
                    "note": "protocol suites; 3dmatch: 5 deg, 0.1 m; eq2: 10 deg (symmetry "
                            "axis when symmetric), 0.02 m; problem files: their metadata",
                },
                "skipped": self.skipped,
                "run": self.run,
                "summary": self.summary,
                "certificates": self.scopes,
            }
        )

    def write(self, out_dir: str | Path, *, plot: bool = False, trials: bool = True,
              markdown: bool = True) -> list[Path]:
        """Write ``summary.csv``, ``bench.json``, ``report.md`` (and plots) to ``out_dir``;
        ``trials=True`` also copies the row file there when it lives elsewhere."""
        from certpose.bench.report import write_csv

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        written = [write_csv(out / "summary.csv", SUMMARY_COLUMNS, self.summary)]
        if trials and self.rows_path.resolve() != (out / "trials.csv").resolve():
            shutil.copyfile(self.rows_path, out / "trials.csv")
            written.append(out / "trials.csv")
        path = out / "bench.json"
        write_json(path, self.to_dict())  # strict JSON: NaN (e.g. no successes) -> null
        written.append(path)
        plots: list[Path] = []
        if plot:
            plots = plot_report(self.summary, self.scopes, out, title=self._title())
            written.extend(plots)
        if markdown:
            written.append(write_markdown(out / "report.md", self.to_dict(), plots,
                                          order=self.config.solvers))
        return written

    def _title(self) -> str:
        suites = sorted({r["suite"] for r in self.summary})
        return f"certpose bench: {', '.join(suites) or Path(self.shape).name}"


# --------------------------------------------------------------------------- solvers


@dataclass(frozen=True)
class _Outcome:
    T: NDArray[np.float64]
    status: str = ""
    reported_time: float = float("nan")
    certificate: Any = None
    success: bool | None = None


def _certpose(**kwargs: Any) -> Callable[[Instance], _Outcome]:
    def run(inst: Instance) -> _Outcome:
        from certpose.api import register

        res = register(inst.source, inst.target, noise_bound=inst.noise_bound,
                       weights=inst.weights, **kwargs)
        return _Outcome(res.T_target_source, res.status.value, res.solve_time, res.certificate,
                        bool(res.success))

    return run


_bench_extra = bench_extra


def _gtsam_gnc(inst: Instance) -> _Outcome:
    gtsam = _bench_extra("gtsam", "the gtsam-gnc peer")

    graph = gtsam.NonlinearFactorGraph()
    model = gtsam.noiseModel.Isotropic.Sigma(3, inst.scalar_noise_bound)
    # error = T * source_k - target_k, whitened by beta: the same residual as certpose's TLS.
    for a, b in zip(inst.source, inst.target, strict=True):
        graph.add(gtsam.KnownLandmarkFactorPose3(0, b, a, model))
    initial = gtsam.Values()
    initial.insert(0, gtsam.Pose3())
    params = gtsam.GncLMParams()
    params.setLossType(gtsam.GncLossType.TLS)
    optimizer = gtsam.GncLMOptimizer(graph, initial, params)
    # GTSAM compares the factor error 0.5 ||r / beta||^2 to the threshold: 0.5 means
    # ||r||^2 / beta^2 <= 1, certpose's TLS truncation (cbar2 = 1).
    optimizer.setInlierCostThresholds(0.5)
    estimate = optimizer.optimize()
    return _Outcome(np.asarray(estimate.atPose3(0).matrix()), "")


@contextlib.contextmanager
def _one_thread_peers(names: Sequence[str]) -> Iterator[None]:
    """Open3D's parallel loops (TBB; every core by default) on one thread inside the block.

    Its RANSAC result depends on the thread count, so this makes the rows a function of the
    seeds whatever ran them (this process or a Dask worker, on any machine), and every solver is
    timed on one thread, as certpose's are. On Dask it also stops each worker's TBB threads from
    competing with the other workers (measured: o3d-ransac 1.3x the CPU time with 2 threads).
    The previous limit is restored on exit (the process may be the user's, or a shared worker).
    """
    if not any(n.startswith("o3d-") for n in names):
        yield
        return
    try:
        import open3d as o3d
    except ImportError:  # reported as a skipped solver by the warm-up
        yield
        return
    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(before)


def _o3d_inputs(inst: Instance) -> tuple[Any, Any, Any]:
    import open3d as o3d

    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(inst.source))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(inst.target))
    k = np.arange(inst.source.shape[0], dtype=np.int32)
    corres = o3d.utility.Vector2iVector(np.column_stack([k, k]))
    return src, dst, corres


def _o3d_ransac(inst: Instance) -> _Outcome:
    import open3d as o3d

    reg = o3d.pipelines.registration
    src, dst, corres = _o3d_inputs(inst)
    res = reg.registration_ransac_based_on_correspondence(
        src,
        dst,
        corres,
        inst.scalar_noise_bound,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9)],
        reg.RANSACConvergenceCriteria(100_000, 0.999),
    )
    return _Outcome(np.asarray(res.transformation), f"fitness={res.fitness:.3f}")


def _o3d_fgr(inst: Instance) -> _Outcome:
    import open3d as o3d

    reg = o3d.pipelines.registration
    src, dst, corres = _o3d_inputs(inst)
    option = reg.FastGlobalRegistrationOption(
        use_absolute_scale=True, decrease_mu=True, maximum_correspondence_distance=inst.scalar_noise_bound
    )
    res = reg.registration_fgr_based_on_correspondence(src, dst, corres, option)
    return _Outcome(np.asarray(res.transformation), f"fitness={res.fitness:.3f}")


def _teaser(inst: Instance) -> _Outcome:
    try:
        import teaserpp_python as tpp
    except ImportError as exc:
        raise ImportError("the teaser++ peer needs teaserpp_python, built from TEASER++'s "
                          "sources (see docs/how-to/teaser.md)") from exc
    params = tpp.RobustRegistrationSolver.Params()
    params.cbar2 = 1.0
    params.noise_bound = inst.scalar_noise_bound
    params.estimate_scaling = False
    params.rotation_estimation_algorithm = (
        tpp.RobustRegistrationSolver.ROTATION_ESTIMATION_ALGORITHM.GNC_TLS)
    params.rotation_gnc_factor = 1.4
    params.rotation_max_iterations = 100
    params.rotation_cost_threshold = 1e-12
    solver = tpp.RobustRegistrationSolver(params)
    solver.solve(np.ascontiguousarray(inst.source.T), np.ascontiguousarray(inst.target.T))
    sol = solver.getSolution()
    # The released binding's solution has rotation, translation and scale; its C++ `valid`
    # flag is not exposed (older builds had it). Judge the solution by what is exposed: the
    # max clique, the translation inliers and the TLS cost of the pose, computed here.
    clique = _binding_list(solver, "getInlierMaxClique")
    t_inliers = _binding_list(solver, "getTranslationInliers")
    flag = getattr(sol, "valid", None)
    ok, status, T = teaser_verdict(inst, np.asarray(sol.rotation, dtype=np.float64),
                                   np.asarray(sol.translation, dtype=np.float64).ravel(),
                                   clique=clique, translation_inliers=t_inliers,
                                   valid=None if flag is None else bool(flag))
    return _Outcome(T, status, success=ok)


def _binding_list(solver: Any, method: str) -> list[int] | None:
    """``solver.method()`` as a list of indices, or None when the binding lacks it."""
    fn = getattr(solver, method, None)
    if fn is None:
        return None
    try:
        return [int(k) for k in np.ravel(np.asarray(fn()))]
    except Exception:  # noqa: BLE001 - a binding without the data: judged without it
        return None


def teaser_verdict(
    inst: Instance, R: NDArray[np.float64], t: NDArray[np.float64], *,
    clique: Sequence[int] | None, translation_inliers: Sequence[int] | None,
    valid: bool | None = None,
) -> tuple[bool, str, NDArray[np.float64]]:
    """Success, status text and ``T_target_source`` of a TEASER++ solution.

    A solve succeeded when its pose is a finite rigid transform, its max clique (when the
    binding exposes it) and its translation inliers keep at least 3 correspondences each (fewer
    fix no pose: TEASER++ then returns an arbitrary one), and the binding's own ``valid`` flag,
    where it exists, agrees. The status names these and the pose's weighted TLS cost on the
    instance (the same cost certpose minimises), so that the peers' rows compare.
    """
    from solvers import WeightedTLSProblem

    T = np.eye(4)
    finite = R.shape == (3, 3) and t.shape == (3,) and bool(np.isfinite(R).all()
                                                           and np.isfinite(t).all())
    rigid = finite and bool(np.allclose(R.T @ R, np.eye(3), atol=1e-6)) and np.linalg.det(R) > 0
    if rigid:
        T[:3, :3], T[:3, 3] = R, t
    problem = WeightedTLSProblem(inst.source, inst.target, noise_bound=inst.noise_bound,
                                 weights=inst.weights)
    cost = problem.cost(T[:3, :3], T[:3, 3]) if rigid else float("nan")
    n_clique = None if clique is None else len(clique)
    n_trans = None if translation_inliers is None else len(translation_inliers)
    enough = all(k is None or k >= 3 for k in (n_clique, n_trans))
    ok = bool(rigid and enough and valid is not False)
    parts = [("solved" if ok else "failed"),
             f"max clique {n_clique if n_clique is not None else 'n/a'}",
             f"translation inliers {n_trans if n_trans is not None else 'n/a'}",
             f"TLS cost {cost:.6g}"]
    if not rigid:
        parts.append("pose not rigid or not finite")
    if valid is not None:
        parts.append(f"valid={valid}")
    return ok, "; ".join(parts), T


SOLVERS: dict[str, Callable[[Instance], _Outcome]] = {
    "gnc": _certpose(prune="auto"),
    "gnc-only": _certpose(prune="never"),
    "gnc+certify": _certpose(certify=True),
    "gnc+cert-pruned": _certpose(certify=True, scope="pruned"),
    "gnc+cert-rotation": _certpose(certify=True, scope="rotation"),
    "sdp": _certpose(solver="sdp"),
    "gtsam-gnc": _gtsam_gnc,
    "o3d-ransac": _o3d_ransac,
    "o3d-fgr": _o3d_fgr,
    "teaser++": _teaser,
}
"""Benchmark solvers by name (see the module docstring)."""

DEFAULT_SOLVERS: tuple[str, ...] = ("gnc", "gnc-only", "gtsam-gnc", "o3d-ransac", "o3d-fgr")
"""Solvers run when none are named (the SDP-based ones are slow and opt-in; ``teaser++`` is
added by ``certpose bench`` when ``teaserpp_python`` is importable)."""


def teaser_available() -> bool:
    """Whether ``teaserpp_python`` can be imported (without importing it)."""
    import importlib.util

    return importlib.util.find_spec("teaserpp_python") is not None


def _seed_peers(seed: int) -> None:
    import open3d as o3d

    o3d.utility.random.seed(int(seed) % (2**31))


# --------------------------------------------------------------------------- running


@dataclass(frozen=True)
class _Task:
    """One instance to make on a worker from its spec, and the solvers still to run on it."""

    spec: InstanceSpec
    solvers: tuple[str, ...]


def suite_name(shape_name: str) -> str:
    """The ``suite`` of the protocol on a shape: the file's stem (``"synthetic"`` built in)."""
    return "synthetic" if shape_name == "synthetic" else Path(shape_name).stem


# Per process: solvers already warmed up, with the reason when one cannot run.
_WARMED: dict[str, str | None] = {}


def _ensure_warm(names: Sequence[str]) -> dict[str, str]:
    """Warm up the solvers not yet run in this process; the skipped ones with the reason."""
    todo = [s for s in names if s not in _WARMED]
    if todo:
        skipped: dict[str, str] = {}
        _warm_up(todo, skipped)
        for s in todo:
            _WARMED[s] = skipped.get(s)
    return {s: why for s in names if (why := _WARMED[s]) is not None}


def _iter_tasks(
    tasks: Sequence[_Task], shapes: dict[str, NDArray[np.float64]], noise: float
) -> Iterator[dict[str, Any]]:
    """Rows of ``tasks``, making each instance from its spec; solver by solver.

    One solver at a time over the instances: interleaving solvers measured slower certpose
    times (cold caches, Open3D's threads still spinning). Open3D runs on one thread
    (:func:`_one_thread_peers`). An instance that cannot be made gives one row per solver with
    the error.
    """
    names = list(dict.fromkeys(s for t in tasks for s in t.solvers))
    skipped = _ensure_warm(names)
    insts: list[Instance | Exception] = []
    for t in tasks:
        try:
            insts.append(load_instance(t.spec, shapes, noise))
        except Exception as exc:  # one bad instance (file) must not stop the run
            reraise_interrupt(exc)
            log.warning("cannot make %s/%s: %s", t.spec.suite, t.spec.instance, exc)
            insts.append(exc)
    with _one_thread_peers(names):
        for name in names:
            if name in skipped:
                continue
            for task, inst in zip(tasks, insts, strict=True):
                if name in task.solvers:
                    yield _run_one(name, inst, task.spec)


def _run_batch(
    tasks: Sequence[_Task], shapes: dict[str, NDArray[np.float64]], noise: float
) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """A Dask task: the rows of ``tasks`` and the solvers this worker could not run."""
    rows = list(_iter_tasks(tasks, shapes, noise))
    names = list(dict.fromkeys(s for t in tasks for s in t.solvers))
    return rows, {s: why for s in names if (why := _WARMED.get(s)) is not None}


def plan_tasks(
    specs: Iterable[InstanceSpec], solvers: Sequence[str], done: set[tuple[str, str, str]]
) -> Iterator[_Task]:
    """The specs with the solvers whose rows are not in ``done`` (keys ``(suite, instance,
    solver)``), one at a time (a grid of any size is never held in memory)."""
    for spec in specs:
        todo = tuple(s for s in solvers if (spec.suite, spec.instance, s) not in done)
        if todo:
            yield _Task(spec, todo)


def _suite_specs(
    config: BenchConfig, shape: NDArray[np.float64] | None, shape_name: str
) -> tuple[Callable[[], Iterator[InstanceSpec]], dict[str, NDArray[np.float64]], dict[str, str]]:
    """A generator function of the specs of every suite of ``config`` (the protocol grids are
    drawn lazily), the protocol shapes by suite, and what each suite was made from (the
    manifest). Files and data folders are checked here, before any work."""
    parts: list[Callable[[], Iterable[InstanceSpec]]] = []
    specs = _Parts(parts)
    shapes: dict[str, NDArray[np.float64]] = {}
    sources: dict[str, str] = {}
    data = Path(config.data_dir) if config.data_dir is not None else default_data_dir()
    grid = (config.n_values, config.outlier_ratios, config.trials, config.seed)
    if not config.suites and not config.problems:
        if shape is None:
            from certpose.io.points import synthetic_shape

            shape = synthetic_shape()
        name = suite_name(shape_name)
        shapes[name] = check_points(shape, "shape", min_points=3)
        sources[name] = shape_name
        specs.lazy(protocol_specs, name, *grid)
    for suite in config.suites:
        if suite == "synthetic":
            from certpose.io.points import synthetic_shape

            shapes[suite], sources[suite] = synthetic_shape(), "synthetic"
            specs.lazy(protocol_specs, suite, *grid)
        elif suite == "bunny":
            from certpose.io.points import load_bunny

            path = Path(shape_name) if shape_name != "synthetic" else data.joinpath(
                "bunny", "bun_zipper_res3.ply")
            if shape is not None and shape_name != "synthetic":
                shapes[suite] = check_points(shape, "shape", min_points=3)
            else:
                if not path.is_file():
                    raise FileNotFoundError(f"the bunny suite needs '{path}' (give the data "
                                            "folder with --data DIR, or the file with --bunny).")
                shapes[suite] = load_bunny(path)
            sources[suite] = str(path)
            specs.lazy(protocol_specs, suite, *grid)
        elif suite == "3dmatch":
            specs += threedmatch_specs(data)
            sources[suite] = str(data / "3dmatch")
        elif suite == "eq2":
            specs += eq2_specs(config.trials, config.seed, data)
            sources[suite] = f"synthetic mug x {config.trials}" + (
                f" + {data / 'ycbv'}" if (data / "ycbv").is_dir() else "")
    for folder in config.problems:
        found = problem_specs(folder)
        name = found[0].suite
        if name in sources:
            raise ValueError(f"--problems '{folder}' is named {name!r} like another suite of "
                             "this run; rename the folder.")
        specs += found
        sources[name] = str(Path(folder).resolve())
    return specs, shapes, sources


class _Parts:
    """Specs from several suites: lists, and protocol grids drawn again on each call."""

    def __init__(self, parts: list[Callable[[], Iterable[InstanceSpec]]]) -> None:
        self.parts = parts

    def __iadd__(self, specs: list[InstanceSpec]) -> _Parts:
        self.parts.append(lambda: specs)
        return self

    def lazy(self, fn: Callable[..., Iterable[InstanceSpec]], *args: Any) -> None:
        self.parts.append(lambda: fn(*args))

    def __call__(self) -> Iterator[InstanceSpec]:
        for part in self.parts:
            yield from part()


def run_benchmark(
    config: BenchConfig,
    *,
    shape: NDArray[np.float64] | None = None,
    shape_name: str = "synthetic",
    progress: bool = True,
    out_dir: str | Path | None = None,
    resume: bool = False,
    force: bool = False,
    workers: int | None = 0,
    scheduler: str | None = None,
    batch_size: int | None = None,
) -> BenchReport:
    """Run every solver of ``config`` on the same instances.

    Parameters
    ----------
    config : BenchConfig
        Suites, grid and solvers.
    shape : (M, 3) ndarray, optional
        Shape points in the unit cube of the protocol suite (no ``config.suites``; or the
        ``bunny`` suite's when ``shape_name`` is a file); default
        :func:`certpose.io.points.synthetic_shape`.
    shape_name : str, optional
        Recorded in the report (e.g. the bunny's path); its stem is the protocol rows' ``suite``
        when ``config.suites`` is empty.
    progress : bool, optional
        Show a tqdm progress bar on stderr.
    out_dir : path, optional
        Stream the rows to ``out_dir/trials.csv`` as they finish (checked before any work);
        default a temporary folder, deleted with the report.
    resume : bool, optional
        Keep the rows of ``out_dir`` and run only the missing ones.
    force : bool, optional
        Overwrite a result set in ``out_dir`` (else :class:`FileExistsError`).
    workers : int or None, optional
        ``0``: run in this process. ``N > 0``: a Dask ``LocalCluster`` of ``N`` single-thread
        worker processes; ``None``: one per CPU core. Ignored with ``scheduler``.
    scheduler : str, optional
        Address of a running Dask scheduler to send the work to.
    batch_size : int, optional
        Protocol instances per Dask task (default: at most 50, fewer towards the end of the
        run so that the workers finish together); the others (files, 3DMatch, eq. (2)) go one
        per task.

    Returns
    -------
    BenchReport
        The summary, computed from the row file (all rows of ``out_dir`` when resuming). A
        solver that raises on an instance is recorded as a failed trial with the error; a
        solver whose backend is missing is listed in ``skipped``.

    Raises
    ------
    BenchInterrupted
        On Ctrl-C, after the finished rows are written.
    """
    from certpose.bench.rows import open_rows

    t_start, cpu_start = time.perf_counter(), time.process_time()
    tqdm = _bench_extra("tqdm", "certpose bench").tqdm
    if workers is not None and workers < 0:
        raise ValueError(f"`workers` must be >= 0 or None, got {workers}.")
    make_specs, shapes, sources = _suite_specs(config, shape, shape_name)

    tmp = None
    if out_dir is None:
        tmp = tempfile.mkdtemp(prefix="certpose-bench-")
        out_dir = tmp
    manifest = {"noise": config.noise, "suites": sources}
    from certpose.io.output import folder_lock

    # One writer per folder: a second run (--resume or not) is refused while this one writes.
    with folder_lock(out_dir, what="bench --out folder"):
        writer, done = open_rows(out_dir, TRIAL_COLUMNS, manifest, resume=resume, force=force)
        try:
            total = n_protocol = 0
            for t in plan_tasks(make_specs(), config.solvers, done):  # counted, not kept
                total += len(t.solvers)
                n_protocol += t.spec.kind == "protocol"
            tasks = plan_tasks(make_specs(), config.solvers, done)
            skipped = _run_tasks(tasks, shapes, config, writer, total=total,
                                 n_protocol=n_protocol, tqdm=tqdm, progress=progress,
                                 workers=workers, scheduler=scheduler, batch_size=batch_size)
        finally:
            writer.close()
    for name, why in skipped.items():
        log.warning("skipping solver %s: %s", name, why)
    summary, scopes = summarize_file(writer.path, order=config.solvers)
    run = {"wall_seconds": time.perf_counter() - t_start, "rows_written": writer.count,
           "workers": "scheduler" if scheduler is not None else (
               os.cpu_count() if workers is None else workers),
           "driver_cpu_seconds": time.process_time() - cpu_start,
           "driver_peak_rss_mb": _peak_rss_mb()}
    report = BenchReport(config, shape_name, writer.path, summary, scopes, skipped, run)
    if tmp is not None:
        weakref.finalize(report, shutil.rmtree, tmp, ignore_errors=True)
    return report


def _run_tasks(
    tasks: Iterator[_Task], shapes: dict[str, NDArray[np.float64]], config: BenchConfig,
    writer: Any, *, total: int, n_protocol: int, tqdm: Any, progress: bool,
    workers: int | None, scheduler: str | None, batch_size: int | None,
) -> dict[str, str]:
    skipped: dict[str, str] = {}
    written = 0

    def emit(rows: list[dict[str, Any]]) -> None:
        nonlocal written
        writer.write_many(rows)  # on disk (fsync) before the next row or batch is run
        written += len(rows)

    try:
        with tqdm(total=total, desc="certpose bench", unit="solve", disable=not progress,
                  leave=False) as bar:
            if total == 0:
                pass
            elif scheduler is None and workers == 0:
                skipped.update(_ensure_warm(config.solvers))
                # In chunks, as on Dask: the instances of one chunk at a time in memory.
                for chunk in _batches(tasks, batch_size or 50):
                    for row in _iter_tasks(chunk, shapes, config.noise):
                        emit([row])
                        bar.update()
            else:
                _run_dask(tasks, shapes, config.noise, n_protocol=n_protocol, workers=workers,
                          scheduler=scheduler, batch_size=batch_size, emit=emit, bar=bar,
                          skipped=skipped)
    except KeyboardInterrupt:
        from certpose.bench.rows import count_rows

        # Count what is on disk: the interrupt may land between a row's write and `emit`'s
        # bookkeeping.
        writer.close()
        written = count_rows(writer.path) - (writer.initial or 0)
        raise BenchInterrupted(
            f"interrupted: {written} new row(s) written to {writer.path}; run again with "
            "--resume to finish."
        ) from None
    return skipped


def _peak_rss_mb() -> float:
    """This process's peak resident set size in MiB (NaN where unknown)."""
    try:
        import resource
    except ImportError:  # not on this platform
        return float("nan")
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0 if os.uname().sysname != "Darwin" else kb / 2**20


class BenchInterrupted(Exception):
    """Ctrl-C during a run: the finished rows are on disk; the message says where."""


def _batches(tasks: Iterable[_Task], size: int, *, n_protocol: int | None = None,
             slots: int = 1) -> Iterator[list[_Task]]:
    """Protocol tasks in chunks of at most ``size`` (cheap: per-task overhead would dominate);
    the others alone (seconds each: they spread over the workers).

    With ``n_protocol`` (how many protocol tasks ``tasks`` holds), chunks shrink towards the end
    (guided self-scheduling): a chunk is at most the protocol tasks left over ``2 * slots``, so
    the last chunks are small and the ``slots`` workers finish together instead of one running a
    full chunk while the others wait (chunks cost up to 1.5x each other: outlier ratios differ).
    """
    left = n_protocol
    chunk: list[_Task] = []
    for t in tasks:
        if t.spec.kind != "protocol":
            yield [t]
            continue
        chunk.append(t)
        cap = size if left is None else max(1, min(size, math.ceil(left / (2 * slots))))
        if len(chunk) >= cap:
            if left is not None:
                left -= len(chunk)
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def _run_dask(
    tasks: Iterable[_Task],
    shapes: dict[str, NDArray[np.float64]],
    noise: float,
    *,
    n_protocol: int,
    workers: int | None,
    scheduler: str | None,
    batch_size: int | None,
    emit: Callable[[list[dict[str, Any]]], None],
    bar: Any,
    skipped: dict[str, str],
) -> None:
    """Send batches of tasks to Dask and emit each row as its batch completes.

    At most a few batches per worker are in flight, so the driver's memory does not grow with
    the number of instances; a batch lost with its worker is retried by Dask elsewhere.
    """
    distributed = _bench_extra("distributed", "certpose bench on Dask")

    if not log.isEnabledFor(logging.DEBUG):
        # Dask logs every cluster start and stop at INFO (set when it is imported).
        logging.getLogger("distributed").setLevel(logging.WARNING)

    if scheduler is not None:
        cluster = None
        client = distributed.Client(scheduler)
    else:
        cluster = _local_cluster(workers or os.cpu_count() or 1)
        client = distributed.Client(cluster)
        # Ctrl-C reaches the whole process group: the driver stops the cluster, the workers
        # must not die first with tracebacks of their own.
        client.run(_ignore_sigint)
    try:
        n_slots = max(sum(client.nthreads().values()), 1)
        if batch_size is not None:
            batches = _batches(tasks, batch_size)
        else:
            batches = _batches(tasks, 50, n_protocol=n_protocol, slots=n_slots)
        # Only protocol suites have shapes; distributed cannot scatter an empty dict (3dmatch,
        # eq2 and --problems runs failed on it).
        shapes_f = client.scatter(shapes, broadcast=True) if shapes else {}

        def submit(batch: Sequence[_Task]) -> Any:
            return client.submit(_run_batch, list(batch), shapes_f, noise, pure=False,
                                 retries=2)

        window = 2 * n_slots
        first = [submit(b) for _, b in zip(range(window), batches, strict=False)]
        pending = distributed.as_completed(first)
        for fut in pending:
            rows, skip = fut.result()
            fut.release()
            skipped.update(skip)
            emit(rows)
            bar.update(len(rows))
            nxt = next(batches, None)
            if nxt is not None:
                pending.add(submit(nxt))
    except KeyboardInterrupt:
        # Workers busy in a solve are killed on close; that is expected, not worth a warning.
        logging.getLogger("distributed").setLevel(logging.CRITICAL)
        # Ctrl-C is answered within a second: the busy workers are not waited for (a worker
        # process exits by itself when its parent does).
        _close_quickly(client, cluster)
        raise
    client.close()
    if cluster is not None:
        cluster.close()


def _close_quickly(client: Any, cluster: Any, timeout: float = 0.3) -> None:
    """Close ``client`` and ``cluster`` within about ``timeout`` seconds each, or give up."""
    for closer in (client, cluster):
        if closer is None:
            continue
        try:
            closer.close(timeout=timeout)
        except BaseException as exc:  # noqa: BLE001 - a timeout or a second Ctrl-C: give up
            log.debug("not closed within %.1f s: %s", timeout, exc)


WORKER_ENV: dict[str, str] = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
}
"""Environment of the embedded cluster's workers: one single-thread worker per core, so no
library may start a thread pool of its own (oversubscribed threads spin against the other
workers). Dask sets the first three by default (``distributed.nanny.pre-spawn-environ``); they
are set here too so that a user's Dask configuration cannot undo them. Open3D ignores them: it is
limited in the process (:func:`_one_thread_peers`)."""


WORKER_CONFIG: dict[str, Any] = {
    "distributed.worker.profile.enabled": False,
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
}
"""Dask configuration of the embedded cluster's workers: no statistical profiler (it samples
every thread's stack every 10 ms for a dashboard this cluster does not have), and glibc's
``malloc`` left at its defaults. Dask starts workers with ``MALLOC_TRIM_THRESHOLD_=65536``
(memory back to the system sooner); setting it also turns off glibc's dynamic ``mmap``
threshold, so every array above 128 kB is mapped afresh and its pages faulted in again on each
allocation. A pose run allocates such arrays all the time: measured over the 60 targets of the
shared YCB-Video frames as a BOP folder, in one process, 6.9 s of system time without the
variable and 26.6 s with it, for the same 95 s of user time."""


def _local_cluster(n_workers: int) -> Any:
    """The embedded cluster: ``n_workers`` single-thread worker processes (solvers hold the
    GIL) with :data:`WORKER_ENV` and :data:`WORKER_CONFIG`; no dashboard, since other users'
    clusters may hold its port."""
    distributed = _bench_extra("distributed", "certpose bench on Dask")
    import dask

    with dask.config.set(WORKER_CONFIG):  # the nannies hand this configuration to the workers
        return distributed.LocalCluster(
            n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None,
            silence_logs=logging.ERROR, env=dict(WORKER_ENV),
        )


def _ignore_sigint() -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _warm_up(solvers: Sequence[str], skipped: dict) -> None:
    """Run each solver once on a throw-away instance (JIT compilation, lazy imports)."""
    from certpose.data.instances import make_instance
    from certpose.io.points import synthetic_shape

    b = make_instance(synthetic_shape(), 50, 0.5, noise=0.01,
                      rng=np.random.default_rng(2**31 - 1))
    inst = Instance(b.source, b.target, None, b.noise_bound, b.rotation, b.translation, 50, 0.5)
    for name in solvers:
        try:
            SOLVERS[name](inst)
        except ImportError as exc:
            skipped[name] = f"cannot import its backend ({exc})"
        except Exception as exc:  # reported per trial by the timed runs
            reraise_interrupt(exc)
            log.warning("warm-up of %s failed: %s", name, exc)


def _axis_error_deg(R: NDArray[np.float64], R_gt: NDArray[np.float64],
                    axis: NDArray[np.float64]) -> float:
    a = axis / np.linalg.norm(axis)
    return math.degrees(math.acos(float(np.clip((R @ a) @ (R_gt @ a), -1.0, 1.0))))


_NAN = float("nan")


def _run_one(name: str, inst: Instance | Exception, spec: InstanceSpec) -> dict[str, Any]:
    rec: dict[str, Any] = {"suite": spec.suite, "instance": spec.instance,
                           "instance_seed": spec.seed, "solver": name, "trial": spec.trial,
                           "n": 0, "outlier_ratio": _NAN}
    fail = dict(success=False, rotation_error_deg=_NAN, translation_error=_NAN,
                reported_time_ms=_NAN, cost=_NAN, status="exception", certified=None,
                cert_problem="", lower_bound=_NAN, upper_bound=_NAN, relative_gap=_NAN)
    if isinstance(inst, Exception):
        rec.update(fail, time_ms=_NAN, status="bad-instance",
                   error=f"{type(inst).__name__}: {inst}")
        return rec
    rec.update(n=inst.n, outlier_ratio=inst.outlier_ratio)
    if name.startswith("o3d-"):
        _seed_peers(spec.seed)  # per instance: the same sample whatever ran before on this worker
    t0 = time.perf_counter()
    try:
        out = SOLVERS[name](inst)
    except Exception as exc:  # a peer failing on one instance must not stop the run
        reraise_interrupt(exc)
        elapsed = time.perf_counter() - t0
        log.warning("%s failed on %s/%s: %s", name, spec.suite, spec.instance, exc)
        rec.update(fail, time_ms=elapsed * 1e3, error=f"{type(exc).__name__}: {exc}")
        return rec
    elapsed = time.perf_counter() - t0
    T = np.asarray(out.T, dtype=np.float64)
    finite = T.shape == (4, 4) and bool(np.all(np.isfinite(T)))
    rot_err = trans_err = cost = _NAN
    if finite:
        cost = float(inst.problem.cost(T[:3, :3], T[:3, 3]))
    if finite and inst.rotation is not None:
        if inst.symmetry_axis is not None:
            rot_err = _axis_error_deg(T[:3, :3], inst.rotation, inst.symmetry_axis)
        else:
            rot_err = rotation_error_deg(T[:3, :3], inst.rotation)
        trans_err = translation_error(T[:3, 3], inst.translation)
        success = bool(rot_err < inst.rotation_tol_deg and trans_err < inst.translation_tol)
    else:  # no ground truth: the solver's own verdict
        success = finite and (out.success is None or out.success)
    cert = out.certificate
    rec.update(
        success=success,
        rotation_error_deg=rot_err,
        translation_error=trans_err,
        time_ms=elapsed * 1e3,
        reported_time_ms=out.reported_time * 1e3,
        cost=cost,
        status=out.status,
        certified=None if cert is None else bool(cert.certified),
        cert_problem="" if cert is None else str(cert.problem),
        lower_bound=_NAN if cert is None else float(cert.lower_bound),
        upper_bound=_NAN if cert is None else float(cert.upper_bound),
        relative_gap=_NAN if cert is None else float(cert.relative_gap),
        error="",
    )
    return rec


def _json_clean(value: Any) -> Any:
    from certpose.io.output import jsonable

    return jsonable(value)


def redraw(results_dir: str | os.PathLike[str]) -> tuple[Any, list[Path]]:
    """Rebuild ``summary.csv``, ``bench.json``, the plots and ``report.md`` of a result folder
    from its ``trials.csv`` and ``run.json``, without solving.

    Returns
    -------
    report : BenchReport
    written : list of Path

    Raises
    ------
    FileNotFoundError
        The folder or its ``trials.csv`` is missing.
    ValueError
        ``trials.csv`` or ``run.json`` is not a certpose bench file.
    """
    from dataclasses import fields

    from certpose.bench.rows import MANIFEST_FILE, ROWS_FILE

    out = Path(results_dir)
    if not out.is_dir():
        raise FileNotFoundError(f"--report folder '{out}' does not exist.")
    rows = out / ROWS_FILE
    if not rows.is_file():
        raise FileNotFoundError(f"--report folder '{out}' holds no {ROWS_FILE} (not a certpose "
                                "bench result folder).")
    config = BenchConfig()
    old: dict[str, Any] = {}
    if (out / "bench.json").is_file():
        try:
            old = json.loads((out / "bench.json").read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"'{out / 'bench.json'}' is not valid JSON ({exc}).") from None
        if not isinstance(old, dict):
            raise ValueError(f"'{out / 'bench.json'}' is not a certpose bench report.")
        cfg = old.get("config") or {}
        known = {f.name for f in fields(BenchConfig)}
        try:
            config = BenchConfig(**{k: (tuple(v) if isinstance(v, list) else v)
                                    for k, v in cfg.items() if k in known})
        except (TypeError, ValueError) as exc:
            raise ValueError(f"'{out / 'bench.json'}' holds an invalid config ({exc}).") from None
    elif (out / MANIFEST_FILE).is_file():
        try:
            json.loads((out / MANIFEST_FILE).read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"'{out / MANIFEST_FILE}' is not valid JSON ({exc}).") from None
    summary, scopes = summarize_file(rows, order=config.solvers)
    if not summary:
        raise ValueError(f"'{rows}' holds no row: nothing to report.")
    report = BenchReport(config, str(old.get("shape", "synthetic")), rows, summary, scopes,
                         dict(old.get("skipped") or {}), dict(old.get("run") or {}))
    return report, report.write(out, plot=True, trials=False)
