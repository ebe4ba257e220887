"""Registration benchmark: certpose's solvers and peers side by side on the same instances.

Protocol (NOTES.md section 3): ``N`` points sampled from a shape scaled into the unit cube, a
random rotation, a translation in the unit ball, isotropic Gaussian noise ``sigma`` on the
inliers, outliers replacing target points with points drawn uniformly in a ball of radius 5,
noise bound ``beta = 5.54 sigma``. A trial succeeds when the rotation error is below 5 degrees
and the translation error below 0.05.

Every solver sees exactly the same instances. Each instance is drawn from its own seed
(:func:`instance_seed`: the run's seed and the instance's place in the grid), in whichever
process runs it: in this process (``workers=0``) or on Dask workers (a ``LocalCluster`` or a
running scheduler), which receive seeds, not arrays. Rows, one per (instance, solver) and keyed
by ``(suite, instance_seed, solver)``, are streamed to ``trials.csv`` as they finish
(:mod:`certpose.bench.rows`), so an interrupted run resumes where it stopped. Times are wall-clock
seconds around each call, including the solver's own conversion of the input arrays (building
a factor graph, Open3D point clouds, validating the problem...); for certpose's solvers the
time the result reports itself (``solve_time``) is recorded too (``reported_time_ms``). Each
solver is run once on a throw-away instance first, so JIT compilation and lazy imports are
not timed. Within a batch (a Dask task, or the whole run in process), the instances are drawn
first and each solver then runs on all of them in turn (not interleaved with the others, which slowed every solver down).

Solvers (:data:`SOLVERS`):

``gnc``
    ``certpose.register`` with automatic max-clique pruning (the front-end).
``gnc-only``
    ``certpose.register(..., prune="never")``: GNC-TLS alone.
``gnc+certify``
    ``certpose.register(..., certify=True)``: the front-end's pose with a certificate.
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
"""

from __future__ import annotations

import csv
import logging
import math
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from certpose.data.instances import NOISE_BOUND_FACTOR, BenchInstance, make_instance
from certpose.io.output import write_json
from solvers.lie import rotation_error_deg, translation_error
from solvers.validation import check_points

__all__ = [
    "SOLVERS",
    "DEFAULT_SOLVERS",
    "BenchConfig",
    "BenchReport",
    "run_benchmark",
    "BenchInterrupted",
    "instance_seed",
    "plan_tasks",
    "summarize",
    "format_table",
]

log = logging.getLogger(__name__)

ROTATION_TOL_DEG = 5.0
TRANSLATION_TOL = 0.05

SUMMARY_COLUMNS = (
    "solver",
    "n",
    "outlier_ratio",
    "trials",
    "success_rate",
    "median_rotation_error_deg",
    "median_translation_error",
    "median_time_ms",
    "median_reported_time_ms",
    "time_vs_gtsam",
    "certified_fraction",
    "median_relative_gap",
    "errors",
)
TRIAL_COLUMNS = (
    "suite",
    "instance_seed",
    "solver",
    "n",
    "outlier_ratio",
    "trial",
    "success",
    "rotation_error_deg",
    "translation_error",
    "time_ms",
    "reported_time_ms",
    "status",
    "certified",
    "relative_gap",
    "error",
)


@dataclass(frozen=True)
class BenchConfig:
    """Grid and protocol of a benchmark run.

    Attributes
    ----------
    n_values : tuple of int
        Numbers of correspondences ``N``.
    outlier_ratios : tuple of float
        Fractions of outliers in ``[0, 1)``.
    noise : float
        Standard deviation ``sigma`` of the inlier noise (unit-cube units).
    trials : int
        Instances per ``(N, outlier ratio)``.
    seed : int
        Seed of the instance generator (the same seed gives the same instances).
    solvers : tuple of str
        Names from :data:`SOLVERS`.
    """

    n_values: tuple[int, ...] = (100,)
    outlier_ratios: tuple[float, ...] = (0.0, 0.5, 0.8, 0.9, 0.95)
    noise: float = 0.01
    trials: int = 10
    seed: int = 0
    solvers: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "n_values", tuple(int(n) for n in self.n_values))
        object.__setattr__(self, "outlier_ratios", tuple(float(r) for r in self.outlier_ratios))
        object.__setattr__(self, "solvers", tuple(self.solvers or DEFAULT_SOLVERS))
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

    @property
    def noise_bound(self) -> float:
        """``beta = 5.54 sigma``."""
        return NOISE_BOUND_FACTOR * self.noise


@dataclass(frozen=True)
class BenchReport:
    """Outcome of :func:`run_benchmark`.

    Attributes
    ----------
    config : BenchConfig
    shape : str
        Where the points came from (a file or ``"synthetic"``).
    trials : list of dict
        One record per solver and instance (keys :data:`TRIAL_COLUMNS`).
    summary : list of dict
        One record per solver, ``N`` and outlier ratio (keys :data:`SUMMARY_COLUMNS`).
    skipped : dict
        Solvers that could not run, with the reason.
    """

    config: BenchConfig
    shape: str
    trials: list[dict[str, Any]]
    summary: list[dict[str, Any]]
    skipped: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (NaN becomes ``None``)."""
        return _json_clean(
            {
                "config": asdict(self.config),
                "noise_bound": self.config.noise_bound,
                "shape": self.shape,
                "success_criterion": {
                    "rotation_error_deg_below": ROTATION_TOL_DEG,
                    "translation_error_below": TRANSLATION_TOL,
                },
                "skipped": self.skipped,
                "summary": self.summary,
                "trials": self.trials,
            }
        )

    def write(
        self, out_dir: str | Path, *, plot: bool = False, trials: bool = True
    ) -> list[Path]:
        """Write ``summary.csv``, ``trials.csv`` and ``bench.json`` (and plots) to ``out_dir``.

        ``trials=False`` leaves ``trials.csv`` alone (a run that streamed its rows there).
        """
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        written = [_write_csv(out / "summary.csv", SUMMARY_COLUMNS, self.summary)]
        if trials:
            written.append(_write_csv(out / "trials.csv", TRIAL_COLUMNS, self.trials))
        path = out / "bench.json"
        write_json(path, self.to_dict())  # strict JSON: NaN (e.g. no successes) -> null
        written.append(path)
        if plot:
            written.extend(plot_report(self, out))
        return written


# --------------------------------------------------------------------------- solvers


@dataclass(frozen=True)
class _Outcome:
    T: NDArray[np.float64]
    status: str = ""
    reported_time: float = float("nan")
    certified: bool | None = None
    relative_gap: float = float("nan")


def _certpose(**kwargs: Any) -> Callable[[BenchInstance], _Outcome]:
    def run(inst: BenchInstance) -> _Outcome:
        from certpose.api import register

        res = register(inst.source, inst.target, noise_bound=inst.noise_bound, **kwargs)
        cert = res.certificate
        return _Outcome(
            res.T_target_source,
            res.status.value,
            res.solve_time,
            None if cert is None else bool(cert.certified),
            float("nan") if cert is None else float(cert.relative_gap),
        )

    return run


def _bench_extra(module: str, what: str) -> Any:
    """Import ``module`` of the ``bench`` extra, or say how to install it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ImportError(f"{what} needs {module.split('.')[0]}, part of the bench extra: "
                          f"pip install 'certpose[bench]'") from exc


def _gtsam_gnc(inst: BenchInstance) -> _Outcome:
    gtsam = _bench_extra("gtsam", "the gtsam-gnc peer")

    graph = gtsam.NonlinearFactorGraph()
    model = gtsam.noiseModel.Isotropic.Sigma(3, inst.noise_bound)
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


def _o3d_inputs(inst: BenchInstance) -> tuple[Any, Any, Any]:
    import open3d as o3d

    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(inst.source))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(inst.target))
    k = np.arange(inst.source.shape[0], dtype=np.int32)
    corres = o3d.utility.Vector2iVector(np.column_stack([k, k]))
    return src, dst, corres


def _o3d_ransac(inst: BenchInstance) -> _Outcome:
    import open3d as o3d

    reg = o3d.pipelines.registration
    src, dst, corres = _o3d_inputs(inst)
    res = reg.registration_ransac_based_on_correspondence(
        src,
        dst,
        corres,
        inst.noise_bound,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9)],
        reg.RANSACConvergenceCriteria(100_000, 0.999),
    )
    return _Outcome(np.asarray(res.transformation), f"fitness={res.fitness:.3f}")


def _o3d_fgr(inst: BenchInstance) -> _Outcome:
    import open3d as o3d

    reg = o3d.pipelines.registration
    src, dst, corres = _o3d_inputs(inst)
    option = reg.FastGlobalRegistrationOption(
        use_absolute_scale=True, decrease_mu=True, maximum_correspondence_distance=inst.noise_bound
    )
    res = reg.registration_fgr_based_on_correspondence(src, dst, corres, option)
    return _Outcome(np.asarray(res.transformation), f"fitness={res.fitness:.3f}")


SOLVERS: dict[str, Callable[[BenchInstance], _Outcome]] = {
    "gnc": _certpose(prune="auto"),
    "gnc-only": _certpose(prune="never"),
    "gnc+certify": _certpose(certify=True),
    "sdp": _certpose(solver="sdp"),
    "gtsam-gnc": _gtsam_gnc,
    "o3d-ransac": _o3d_ransac,
    "o3d-fgr": _o3d_fgr,
}
"""Benchmark solvers by name (see the module docstring)."""

DEFAULT_SOLVERS: tuple[str, ...] = ("gnc", "gnc-only", "gtsam-gnc", "o3d-ransac", "o3d-fgr")
"""Solvers run when none are named (the SDP-based ones are slow and opt-in)."""

def _seed_peers(seed: int) -> None:
    import open3d as o3d

    o3d.utility.random.seed(int(seed) % (2**31))


# --------------------------------------------------------------------------- running


@dataclass(frozen=True)
class _Task:
    """One instance to draw on a worker from its seed, and the solvers still to run on it."""

    n: int
    ratio: float
    trial: int
    seed: int
    solvers: tuple[str, ...]


def instance_seed(seed: int, n: int, ratio: float, trial: int) -> int:
    """Seed of one instance, from the run's seed and the instance's place in the grid.

    Independent of the order instances are drawn in, so any worker can draw any instance, and
    a resumed run draws the same ones. Non-negative and below ``2**63`` (a pandas ``int64``).
    """
    ss = np.random.SeedSequence([int(seed), int(n), round(float(ratio) * 1e9), int(trial)])
    return int(ss.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


def suite_name(shape_name: str) -> str:
    """The ``suite`` column: the shape file's stem (``"synthetic"`` for the built-in one)."""
    return "synthetic" if shape_name == "synthetic" else Path(shape_name).stem


# Per process: solvers already warmed up, with the reason when one cannot run.
_WARMED: dict[str, str | None] = {}


def _ensure_warm(names: Sequence[str], shape: NDArray[np.float64], noise: float) -> dict[str, str]:
    """Warm up the solvers not yet run in this process; the skipped ones with the reason."""
    todo = [s for s in names if s not in _WARMED]
    if todo:
        skipped: dict[str, str] = {}
        _warm_up(todo, shape, noise, skipped)
        for s in todo:
            _WARMED[s] = skipped.get(s)
    return {s: why for s in names if (why := _WARMED[s]) is not None}


def _iter_tasks(
    tasks: Sequence[_Task], shape: NDArray[np.float64], noise: float, suite: str
) -> Iterator[dict[str, Any]]:
    """Rows of ``tasks``, drawing each instance from its seed; solver by solver.

    One solver at a time over the instances: interleaving solvers measured slower certpose
    times (cold caches, Open3D's OpenMP threads still spinning).
    """
    names = list(dict.fromkeys(s for t in tasks for s in t.solvers))
    skipped = _ensure_warm(names, shape, noise)
    insts = [make_instance(shape, t.n, t.ratio, noise=noise, rng=t.seed) for t in tasks]
    for name in names:
        if name in skipped:
            continue
        for task, inst in zip(tasks, insts, strict=True):
            if name in task.solvers:
                row = _run_one(name, inst, task.n, task.ratio, task.trial, seed=task.seed)
                row["suite"] = suite
                yield row


def _run_batch(
    tasks: Sequence[_Task], shape: NDArray[np.float64], noise: float, suite: str
) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """A Dask task: the rows of ``tasks`` and the solvers this worker could not run."""
    rows = list(_iter_tasks(tasks, shape, noise, suite))
    names = list(dict.fromkeys(s for t in tasks for s in t.solvers))
    return rows, {s: why for s in names if (why := _WARMED.get(s)) is not None}


def plan_tasks(config: BenchConfig, done: set[tuple[str, int, str]], suite: str) -> list[_Task]:
    """Instances of ``config``'s grid with the solvers whose rows are not in ``done``."""
    tasks = []
    for n in config.n_values:
        for ratio in config.outlier_ratios:
            for trial in range(config.trials):
                seed = instance_seed(config.seed, n, ratio, trial)
                todo = tuple(s for s in config.solvers if (suite, seed, s) not in done)
                if todo:
                    tasks.append(_Task(n, ratio, trial, seed, todo))
    return tasks


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
        Grid, protocol and solvers.
    shape : (M, 3) ndarray, optional
        Shape points in the unit cube; default :func:`certpose.io.points.synthetic_shape`.
    shape_name : str, optional
        Recorded in the report (e.g. the bunny's path); its stem is the rows' ``suite``.
    progress : bool, optional
        Show a tqdm progress bar on stderr.
    out_dir : path, optional
        Stream the rows to ``out_dir/trials.csv`` as they finish (checked before any work).
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
        Instances per Dask task (default: at most 25, at least 4 tasks per worker).

    Returns
    -------
    BenchReport
        Per-trial records (all rows of ``out_dir`` when streaming) and per-(solver, N, ratio)
        aggregates. A solver that raises on an instance is recorded as a failed trial with the
        error; a solver whose backend is missing is listed in ``skipped``.

    Raises
    ------
    BenchInterrupted
        On Ctrl-C, after the finished rows are written.
    """
    tqdm = _bench_extra("tqdm", "certpose bench").tqdm

    if shape is None:
        from certpose.io.points import synthetic_shape

        shape = synthetic_shape()
    shape = check_points(shape, "shape", min_points=3)
    if workers is not None and workers < 0:
        raise ValueError(f"`workers` must be >= 0 or None, got {workers}.")
    suite = suite_name(shape_name)

    writer = None
    records: list[dict[str, Any]] = []
    if out_dir is not None:
        from certpose.bench.rows import open_rows

        manifest = {"shape": shape_name, "noise": config.noise, "suite": suite}
        writer, records = open_rows(out_dir, TRIAL_COLUMNS, manifest, resume=resume, force=force)
    done = {(str(r["suite"]), int(r["instance_seed"]), str(r["solver"])) for r in records}
    n_before = len(records)
    tasks = plan_tasks(config, done, suite)
    total = sum(len(t.solvers) for t in tasks)

    skipped: dict[str, str] = {}
    written = 0

    def emit(rows: list[dict[str, Any]]) -> None:
        nonlocal written
        if writer is not None:
            writer.write_many(rows)  # on disk (fsync) before the next row or batch is run
        records.extend(rows)
        written += len(rows)

    try:
        with tqdm(total=total, desc="certpose bench", unit="solve", disable=not progress,
                  leave=False) as bar:
            if not tasks:
                pass
            elif scheduler is None and workers == 0:
                skipped.update(_ensure_warm(config.solvers, shape, config.noise))
                for row in _iter_tasks(tasks, shape, config.noise, suite):
                    emit([row])
                    bar.update()
            else:
                _run_dask(tasks, shape, config.noise, suite, workers=workers,
                          scheduler=scheduler, batch_size=batch_size, emit=emit, bar=bar,
                          skipped=skipped)
    except KeyboardInterrupt:
        where = ""
        if writer is not None:
            # Count what is on disk: the interrupt may land between a row's write and `emit`'s
            # bookkeeping.
            from certpose.bench.rows import read_rows

            writer.close()
            written = len(read_rows(writer.path, TRIAL_COLUMNS)) - n_before
            where = f" to {writer.path}"
        raise BenchInterrupted(
            f"interrupted: {written} new row(s) written{where}"
            + ("; run again with --resume to finish." if writer is not None else ".")
        ) from None
    finally:
        if writer is not None:
            writer.close()
    if skipped:
        for name, why in skipped.items():
            log.warning("skipping solver %s: %s", name, why)
    order = {s: i for i, s in enumerate(config.solvers)}
    records.sort(key=lambda r: (r["n"], r["outlier_ratio"], order.get(r["solver"], 99),
                                r["trial"], r["suite"]))
    return BenchReport(config, shape_name, records, summarize(records), skipped)


class BenchInterrupted(Exception):
    """Ctrl-C during a run: the finished rows are on disk; the message says where."""


def _run_dask(
    tasks: Sequence[_Task],
    shape: NDArray[np.float64],
    noise: float,
    suite: str,
    *,
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
    import os

    if not log.isEnabledFor(logging.DEBUG):
        # Dask logs every cluster start and stop at INFO (set when it is imported).
        logging.getLogger("distributed").setLevel(logging.WARNING)

    if scheduler is not None:
        cluster = None
        client = distributed.Client(scheduler)
    else:
        n_workers = workers or os.cpu_count() or 1
        # One single-thread process per core: solvers hold the GIL; no dashboard, since
        # other users' clusters may hold its port.
        cluster = distributed.LocalCluster(
            n_workers=n_workers, threads_per_worker=1, processes=True,
            dashboard_address=None, silence_logs=logging.ERROR,
        )
        client = distributed.Client(cluster)
        # Ctrl-C reaches the whole process group: the driver stops the cluster, the workers
        # must not die first with tracebacks of their own.
        client.run(_ignore_sigint)
    try:
        n_slots = max(sum(client.nthreads().values()), 1)
        size = batch_size or max(1, min(25, math.ceil(len(tasks) / (4 * n_slots))))
        batches = (tasks[i : i + size] for i in range(0, len(tasks), size))
        shape_f = client.scatter(shape, broadcast=True)

        def submit(batch: Sequence[_Task]) -> Any:
            return client.submit(_run_batch, list(batch), shape_f, noise, suite, pure=False,
                                 retries=2)

        window = 4 * n_slots
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
        raise
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _ignore_sigint() -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _warm_up(
    solvers: Sequence[str], shape: NDArray[np.float64], noise: float, skipped: dict
) -> None:
    """Run each solver once on a throw-away instance (JIT compilation, lazy imports)."""
    inst = make_instance(shape, 50, 0.5, noise=noise, rng=np.random.default_rng(2**31 - 1))
    for name in solvers:
        try:
            SOLVERS[name](inst)
        except ImportError as exc:
            skipped[name] = f"cannot import its backend ({exc})"
        except Exception as exc:  # reported per trial by the timed runs
            log.warning("warm-up of %s failed: %s", name, exc)


def _run_one(
    name: str, inst: BenchInstance, n: int, ratio: float, trial: int, *, seed: int
) -> dict[str, Any]:
    rec: dict[str, Any] = {"instance_seed": seed, "solver": name, "n": n,
                           "outlier_ratio": ratio, "trial": trial}
    if name.startswith("o3d-"):
        _seed_peers(seed)  # per instance: the same sample whatever ran before on this worker
    t0 = time.perf_counter()
    try:
        out = SOLVERS[name](inst)
    except Exception as exc:  # a peer failing on one instance must not stop the run
        elapsed = time.perf_counter() - t0
        log.warning("%s failed on N=%d ratio=%g trial %d: %s", name, n, ratio, trial, exc)
        rec.update(
            success=False,
            rotation_error_deg=float("nan"),
            translation_error=float("nan"),
            time_ms=elapsed * 1e3,
            reported_time_ms=float("nan"),
            status="exception",
            certified=None,
            relative_gap=float("nan"),
            error=f"{type(exc).__name__}: {exc}",
        )
        return rec
    elapsed = time.perf_counter() - t0
    T = np.asarray(out.T, dtype=np.float64)
    if T.shape == (4, 4) and np.all(np.isfinite(T)):
        rot_err = rotation_error_deg(T[:3, :3], inst.rotation)
        trans_err = translation_error(T[:3, 3], inst.translation)
    else:
        rot_err = trans_err = float("nan")
    rec.update(
        success=bool(rot_err < ROTATION_TOL_DEG and trans_err < TRANSLATION_TOL),
        rotation_error_deg=rot_err,
        translation_error=trans_err,
        time_ms=elapsed * 1e3,
        reported_time_ms=out.reported_time * 1e3,
        status=out.status,
        certified=out.certified,
        relative_gap=out.relative_gap,
        error="",
    )
    return rec


def _median(values: Sequence[float]) -> float:
    arr = np.asarray([v for v in values if v is not None], dtype=np.float64)
    arr = arr[np.isfinite(arr)]
    return float(np.median(arr)) if arr.size else float("nan")


def summarize(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Aggregate per-trial records by (solver, N, outlier ratio).

    ``time_vs_gtsam`` is the solver's median time over ``gtsam-gnc``'s on the same instances
    (NaN without ``gtsam-gnc``); ``certified_fraction`` and ``median_relative_gap`` are NaN
    for solvers that return no certificate.
    """
    groups: dict[tuple[str, int, float], list[dict[str, Any]]] = {}
    for rec in records:
        groups.setdefault((rec["solver"], rec["n"], rec["outlier_ratio"]), []).append(rec)
    gtsam_time = {
        (n, r): _median([x["time_ms"] for x in recs])
        for (s, n, r), recs in groups.items()
        if s == "gtsam-gnc"
    }
    rows = []
    for (solver, n, ratio), recs in groups.items():
        med_time = _median([x["time_ms"] for x in recs])
        certs = [x["certified"] for x in recs if x["certified"] is not None]
        rows.append(
            {
                "solver": solver,
                "n": n,
                "outlier_ratio": ratio,
                "trials": len(recs),
                "success_rate": float(np.mean([x["success"] for x in recs])),
                "median_rotation_error_deg": _median([x["rotation_error_deg"] for x in recs]),
                "median_translation_error": _median([x["translation_error"] for x in recs]),
                "median_time_ms": med_time,
                "median_reported_time_ms": _median([x["reported_time_ms"] for x in recs]),
                "time_vs_gtsam": med_time / gtsam_time[(n, ratio)]
                if (n, ratio) in gtsam_time and gtsam_time[(n, ratio)] > 0
                else float("nan"),
                "certified_fraction": float(np.mean(certs)) if certs else float("nan"),
                "median_relative_gap": _median([x["relative_gap"] for x in recs]),
                "errors": sum(1 for x in recs if x["error"]),
            }
        )
    return rows


# --------------------------------------------------------------------------- output


def format_table(report: BenchReport) -> str:
    """A fixed-width text table of the summary (one line per solver, N and ratio)."""
    head = (
        f"{'solver':<12} {'N':>5} {'outl':>5} {'succ%':>6} {'rot_deg':>8} {'trans':>8} "
        f"{'time_ms':>9} {'vs_gtsam':>9} {'cert%':>6} {'gap':>9}"
    )
    lines = [head, "-" * len(head)]
    rows = sorted(report.summary, key=lambda r: (r["n"], r["outlier_ratio"]))
    order = {s: i for i, s in enumerate(report.config.solvers)}
    rows.sort(key=lambda r: (r["n"], r["outlier_ratio"], order.get(r["solver"], 99)))
    last = None
    for r in rows:
        if last is not None and (r["n"], r["outlier_ratio"]) != last:
            lines.append("")
        last = (r["n"], r["outlier_ratio"])
        cert = r["certified_fraction"]
        lines.append(
            f"{r['solver']:<12} {r['n']:>5} {r['outlier_ratio']:>5.2f} "
            f"{100 * r['success_rate']:>6.1f} {r['median_rotation_error_deg']:>8.3f} "
            f"{r['median_translation_error']:>8.4f} {_fmt_time(r['median_time_ms']):>9} "
            f"{_fmt(r['time_vs_gtsam'], '.4f'):>9} "
            f"{_fmt(100 * cert if math.isfinite(cert) else cert, '.1f'):>6} "
            f"{_fmt(r['median_relative_gap'], '.2e'):>9}"
            + (f"  ({r['errors']} error(s))" if r["errors"] else "")
        )
    if report.skipped:
        lines.append("")
        lines.extend(f"skipped {name}: {why}" for name, why in report.skipped.items())
    return "\n".join(lines)


def _fmt(x: float, spec: str) -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, spec)


def _fmt_time(ms: float) -> str:
    if not math.isfinite(ms):
        return "-"
    return f"{ms:.3f}" if ms < 10 else f"{ms:.1f}"


def plot_report(report: BenchReport, out_dir: str | Path) -> list[Path]:
    """Write ``bench.png`` (success and time vs outlier ratio) and, when certificates exist,
    ``tightness.png`` (relative gap vs outlier ratio)."""
    matplotlib = _bench_extra("matplotlib", "the benchmark plots")
    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    rows = report.summary
    keys = sorted({(r["solver"], r["n"]) for r in rows}, key=lambda k: (k[1], k[0]))
    fig, (ax_s, ax_t) = plt.subplots(1, 2, figsize=(11, 4.2))
    for solver, n in keys:
        sel = sorted((r for r in rows if r["solver"] == solver and r["n"] == n),
                     key=lambda r: r["outlier_ratio"])
        x = [r["outlier_ratio"] for r in sel]
        label = f"{solver} (N={n})"
        ax_s.plot(x, [100 * r["success_rate"] for r in sel], marker="o", label=label)
        ax_t.plot(x, [r["median_time_ms"] for r in sel], marker="o", label=label)
    ax_s.set(xlabel="outlier ratio", ylabel="success rate [%]", ylim=(-5, 105),
             title="success (rot < 5 deg, trans < 0.05)")
    ax_t.set(xlabel="outlier ratio", ylabel="median time [ms]", yscale="log", title="time")
    for ax in (ax_s, ax_t):
        ax.grid(True, alpha=0.3)
    ax_t.legend(fontsize=7, loc="best")
    fig.suptitle(f"certpose bench: {Path(report.shape).name}, sigma={report.config.noise:g}")
    fig.tight_layout()
    written = [out / "bench.png"]
    fig.savefig(written[0], dpi=120)
    plt.close(fig)

    gap_rows = [r for r in rows if math.isfinite(r["median_relative_gap"])]
    if gap_rows:
        fig, ax = plt.subplots(figsize=(5.5, 4.2))
        for solver, n in sorted({(r["solver"], r["n"]) for r in gap_rows}):
            sel = [r for r in report.trials if r["solver"] == solver and r["n"] == n
                   and r["relative_gap"] is not None and math.isfinite(r["relative_gap"])]
            ax.scatter([r["outlier_ratio"] for r in sel],
                       [max(r["relative_gap"], 1e-12) for r in sel], s=12, alpha=0.6,
                       label=f"{solver} (N={n})")
        ax.set(xlabel="outlier ratio", ylabel="relative duality gap (floored at 1e-12)",
               yscale="log",
               title="tightness of the relaxation")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        written.append(out / "tightness.png")
        fig.savefig(written[-1], dpi=120)
        plt.close(fig)
    return written


def _write_csv(path: Path, columns: Sequence[str], rows: Sequence[dict[str, Any]]) -> Path:
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(columns), extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in columns})
    return path


def _json_clean(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _json_clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_clean(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, (np.integer, np.bool_)):
        return value.item()
    return value
