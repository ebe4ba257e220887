"""Registration benchmark: certpose's solvers and peers side by side on the same instances.

Protocol (NOTES.md section 3): ``N`` points sampled from a shape scaled into the unit cube, a
random rotation, a translation in the unit ball, isotropic Gaussian noise ``sigma`` on the
inliers, outliers replacing target points with points drawn uniformly in a ball of radius 5,
noise bound ``beta = 5.54 sigma``. A trial succeeds when the rotation error is below 5 degrees
and the translation error below 0.05.

Every solver sees exactly the same instances, in the same process. Times are wall-clock
seconds around each call, including the solver's own conversion of the input arrays (building
a factor graph, Open3D point clouds, validating the problem...); for certpose's solvers the
time the result reports itself (``solve_time``) is recorded too (``reported_time_ms``). Each
solver is run once on a throw-away instance first, so JIT compilation and lazy imports are
not timed. Within a grid cell, the cell's instances are drawn first and each solver then runs
on all of them in turn (not interleaved with the others, which slowed every solver down).

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
from collections.abc import Callable, Sequence
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

    def write(self, out_dir: str | Path, *, plot: bool = False) -> list[Path]:
        """Write ``summary.csv``, ``trials.csv`` and ``bench.json`` (and plots) to ``out_dir``."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        written = [
            _write_csv(out / "summary.csv", SUMMARY_COLUMNS, self.summary),
            _write_csv(out / "trials.csv", TRIAL_COLUMNS, self.trials),
        ]
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


def run_benchmark(
    config: BenchConfig,
    *,
    shape: NDArray[np.float64] | None = None,
    shape_name: str = "synthetic",
    progress: bool = True,
) -> BenchReport:
    """Run every solver of ``config`` on the same instances.

    Parameters
    ----------
    config : BenchConfig
        Grid, protocol and solvers.
    shape : (M, 3) ndarray, optional
        Shape points in the unit cube; default :func:`certpose.io.points.synthetic_shape`.
    shape_name : str, optional
        Recorded in the report (e.g. the bunny's path).
    progress : bool, optional
        Show a tqdm progress bar on stderr.

    Returns
    -------
    BenchReport
        Per-trial records and per-(solver, N, ratio) aggregates. A solver that raises on an
        instance is recorded as a failed trial with the error; a solver whose backend is
        missing is listed in ``skipped``.
    """
    tqdm = _bench_extra("tqdm", "certpose bench").tqdm

    if shape is None:
        from certpose.io.points import synthetic_shape

        shape = synthetic_shape()
    shape = check_points(shape, "shape", min_points=3)

    skipped: dict[str, str] = {}
    solvers = list(config.solvers)
    _warm_up(solvers, shape, config, skipped)
    solvers = [s for s in solvers if s not in skipped]

    rng = np.random.default_rng(config.seed)
    _seed_peers(config.seed)
    grid = [(n, r) for n in config.n_values for r in config.outlier_ratios]
    records: list[dict[str, Any]] = []
    with tqdm(
        total=len(grid) * config.trials * max(len(solvers), 1),
        desc="certpose bench",
        unit="solve",
        disable=not progress,
        leave=False,
    ) as bar:
        for n, ratio in grid:
            cell = [
                make_instance(shape, n, ratio, noise=config.noise, rng=rng)
                for _ in range(config.trials)
            ]
            # One solver at a time over the cell's instances: interleaving solvers measured
            # slower certpose times (cold caches, Open3D's OpenMP threads still spinning).
            for name in solvers:
                bar.set_postfix_str(f"N={n} outliers={ratio:g} {name}", refresh=False)
                for trial, inst in enumerate(cell):
                    records.append(_run_one(name, inst, n, ratio, trial))
                    bar.update()
    return BenchReport(config, shape_name, records, summarize(records), skipped)


def _warm_up(
    solvers: Sequence[str], shape: NDArray[np.float64], config: BenchConfig, skipped: dict
) -> None:
    """Run each solver once on a throw-away instance (JIT compilation, lazy imports)."""
    n = min(min(config.n_values), 50)
    inst = make_instance(shape, n, 0.5, noise=config.noise, rng=np.random.default_rng(2**31 - 1))
    for name in solvers:
        try:
            SOLVERS[name](inst)
        except ImportError as exc:
            skipped[name] = f"cannot import its backend ({exc})"
            log.warning("skipping solver %s: %s", name, skipped[name])
        except Exception as exc:  # reported per trial by the timed runs
            log.warning("warm-up of %s failed: %s", name, exc)


def _run_one(name: str, inst: BenchInstance, n: int, ratio: float, trial: int) -> dict[str, Any]:
    rec: dict[str, Any] = {"solver": name, "n": n, "outlier_ratio": ratio, "trial": trial}
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
