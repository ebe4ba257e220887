"""Benchmark reports from the row file: summary table, JSON, PNG plots and a Markdown report.

Everything here is computed by streaming ``trials.csv`` (:func:`summarize_file`): one row at a
time into per-cell accumulators of floats, so the memory grows with the number of cells and
the floats of their medians, not with row dictionaries. ``certpose bench --report DIR``
(:func:`certpose.bench.runner.redraw`) rebuilds every output of a result folder from its rows, without solving.
"""

from __future__ import annotations

import csv
import math
import os
import platform
from array import array
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "SUMMARY_COLUMNS",
    "SCOPE_COLUMNS",
    "summarize",
    "summarize_file",
    "format_table",
    "format_scopes",
    "plot_report",
    "write_markdown",
    "write_csv",
]

SUMMARY_COLUMNS = (
    "suite",
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
    "median_cost",
    "certified_fraction",
    "median_relative_gap",
    "errors",
)
SCOPE_COLUMNS = (
    "suite",
    "solver",
    "cert_problem",
    "outlier_ratio",
    "certificates",
    "certified_fraction",
    "median_relative_gap",
    "max_relative_gap",
)
_SERIES = ("rotation_error_deg", "translation_error", "time_ms", "reported_time_ms", "cost",
           "relative_gap")


class _Cell:
    """Counts and float series of one group of rows."""

    __slots__ = ("count", "success", "certs", "certified", "errors", "series")

    def __init__(self, names: Sequence[str]) -> None:
        self.count = self.success = self.certs = self.certified = self.errors = 0
        self.series = {k: array("d") for k in names}

    def add(self, row: dict[str, Any], names: Sequence[str]) -> None:
        self.count += 1
        self.success += bool(row["success"])
        if row["certified"] is not None:
            self.certs += 1
            self.certified += bool(row["certified"])
        self.errors += bool(row["error"])
        for k in names:
            v = row[k]
            if v is not None and math.isfinite(v):
                self.series[k].append(v)


def _median(a: array) -> float:
    return float(np.median(np.frombuffer(a, dtype=np.float64))) if len(a) else float("nan")


def _max(a: array) -> float:
    return float(np.max(np.frombuffer(a, dtype=np.float64))) if len(a) else float("nan")


def summarize(
    rows: Iterable[dict[str, Any]], *, order: Sequence[str] = ()
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Aggregate rows (any iterable: a file is read one row at a time).

    Returns
    -------
    summary : list of dict
        Per ``(suite, solver, N, outlier ratio)``, keys :data:`SUMMARY_COLUMNS`.
        ``time_vs_gtsam`` is the solver's median time over ``gtsam-gnc``'s in the same cell
        (NaN without it); ``certified_fraction`` and ``median_relative_gap`` are NaN for
        solvers that return no certificate.
    scopes : list of dict
        Per ``(suite, solver, certificate problem, outlier ratio)`` of the rows with a
        certificate, keys :data:`SCOPE_COLUMNS`.
    """
    cells: dict[tuple[str, str, int, float], _Cell] = {}
    scopes: dict[tuple[str, str, str, float], _Cell] = {}
    for row in rows:
        key = (row["suite"], row["solver"], row["n"], row["outlier_ratio"])
        cell = cells.get(key)
        if cell is None:
            cell = cells[key] = _Cell(_SERIES)
        cell.add(row, _SERIES)
        if row["certified"] is not None:
            skey = (row["suite"], row["solver"], row["cert_problem"], row["outlier_ratio"])
            sc = scopes.get(skey)
            if sc is None:
                sc = scopes[skey] = _Cell(("relative_gap",))
            sc.add(row, ("relative_gap",))
    gtsam = {(s, n, r): _median(c.series["time_ms"])
             for (s, solver, n, r), c in cells.items() if solver == "gtsam-gnc"}
    rank = {s: i for i, s in enumerate(order)}

    def sort_key(k: tuple) -> tuple:
        r = k[3]
        return (k[0], k[2], math.inf if math.isnan(r) else r, rank.get(k[1], len(rank)), k[1])

    summary = []
    for key in sorted(cells, key=sort_key):
        suite, solver, n, ratio = key
        c = cells[key]
        med = _median(c.series["time_ms"])
        g = gtsam.get((suite, n, ratio), float("nan"))
        summary.append({
            "suite": suite, "solver": solver, "n": n, "outlier_ratio": ratio,
            "trials": c.count,
            "success_rate": c.success / c.count,
            "median_rotation_error_deg": _median(c.series["rotation_error_deg"]),
            "median_translation_error": _median(c.series["translation_error"]),
            "median_time_ms": med,
            "median_reported_time_ms": _median(c.series["reported_time_ms"]),
            "time_vs_gtsam": med / g if g > 0 else float("nan"),
            "median_cost": _median(c.series["cost"]),
            "certified_fraction": c.certified / c.certs if c.certs else float("nan"),
            "median_relative_gap": _median(c.series["relative_gap"]),
            "errors": c.errors,
        })
    scope_rows = []
    for key in sorted(scopes, key=sort_key):
        suite, solver, problem, ratio = key
        c = scopes[key]
        scope_rows.append({
            "suite": suite, "solver": solver, "cert_problem": problem, "outlier_ratio": ratio,
            "certificates": c.certs, "certified_fraction": c.certified / c.certs,
            "median_relative_gap": _median(c.series["relative_gap"]),
            "max_relative_gap": _max(c.series["relative_gap"]),
        })
    return summary, scope_rows


def summarize_file(path: str | os.PathLike[str], *, order: Sequence[str] = ()
                   ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """:func:`summarize` of a row file, read one row at a time."""
    from certpose.bench.rows import TRIAL_COLUMNS, iter_rows

    return summarize(iter_rows(path, TRIAL_COLUMNS), order=order)


# --------------------------------------------------------------------------- text


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, spec)


def _fmt_time(ms: float) -> str:
    if not math.isfinite(ms):
        return "-"
    return f"{ms:.3f}" if ms < 10 else f"{ms:.1f}"


def _ratio(r: float) -> str:
    return "-" if not math.isfinite(r) else f"{r:.2f}"


def format_table(summary: Sequence[dict[str, Any]], skipped: dict[str, str] | None = None) -> str:
    """A fixed-width text table of the summary (one line per suite, solver, N and ratio)."""
    head = (
        f"{'suite':<12} {'solver':<17} {'N':>5} {'outl':>5} {'succ%':>6} {'rot_deg':>8} "
        f"{'trans':>8} {'time_ms':>9} {'vs_gtsam':>9} {'cost':>9} {'cert%':>6} {'gap':>9}"
    )
    lines = [head, "-" * len(head)]
    last = None
    for r in summary:
        cell = (r["suite"], r["n"], r["outlier_ratio"])
        if last is not None and cell != last:
            lines.append("")
        last = cell
        cert = r["certified_fraction"]
        lines.append(
            f"{r['suite'][:12]:<12} {r['solver']:<17} {r['n']:>5} {_ratio(r['outlier_ratio']):>5} "
            f"{100 * r['success_rate']:>6.1f} {_fmt(r['median_rotation_error_deg'], '.3f'):>8} "
            f"{_fmt(r['median_translation_error'], '.4f'):>8} "
            f"{_fmt_time(r['median_time_ms']):>9} {_fmt(r['time_vs_gtsam'], '.4f'):>9} "
            f"{_fmt(r['median_cost'], '.4g'):>9} "
            f"{_fmt(100 * cert if math.isfinite(cert) else cert, '.1f'):>6} "
            f"{_fmt(r['median_relative_gap'], '.2e'):>9}"
            + (f"  ({r['errors']} error(s))" if r["errors"] else "")
        )
    if skipped:
        lines.append("")
        lines.extend(f"skipped {name}: {why}" for name, why in skipped.items())
    return "\n".join(lines)


def format_scopes(scopes: Sequence[dict[str, Any]]) -> str:
    """Certified fraction and gaps per certificate problem (empty without certificates)."""
    if not scopes:
        return ""
    head = (f"{'suite':<12} {'solver':<17} {'certificate problem':<24} {'outl':>5} {'certs':>6} "
            f"{'cert%':>6} {'med gap':>9} {'max gap':>9}")
    lines = [head, "-" * len(head)]
    for r in scopes:
        lines.append(
            f"{r['suite'][:12]:<12} {r['solver']:<17} {r['cert_problem'][:24]:<24} "
            f"{_ratio(r['outlier_ratio']):>5} {r['certificates']:>6} "
            f"{100 * r['certified_fraction']:>6.1f} {_fmt(r['median_relative_gap'], '.2e'):>9} "
            f"{_fmt(r['max_relative_gap'], '.2e'):>9}"
        )
    return "\n".join(lines)


# --------------------------------------------------------------------------- files


def write_csv(path: Path, columns: Sequence[str], rows: Sequence[dict[str, Any]]) -> Path:
    """A CSV file of ``rows`` (``None`` as an empty cell), written atomically."""
    from certpose.io.output import atomic_path

    with atomic_path(path) as tmp, tmp.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(columns), extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in columns})
    return path


def plot_report(
    summary: Sequence[dict[str, Any]], scopes: Sequence[dict[str, Any]], out_dir: str | Path,
    *, title: str = "certpose bench",
) -> list[Path]:
    """Write ``bench.png`` (success rate and median time against the outlier ratio, one line
    per suite, solver and N) and, when certificates exist, ``certificates.png`` (certified
    fraction and median relative gap per certificate problem)."""
    from certpose.bench.rows import bench_extra

    matplotlib = bench_extra("matplotlib", "the benchmark plots")
    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    rows = [r for r in summary if math.isfinite(r["outlier_ratio"])]
    keys = sorted({(r["suite"], r["solver"], r["n"]) for r in rows})
    many_suites = len({k[0] for k in keys}) > 1
    fig, (ax_s, ax_t) = plt.subplots(1, 2, figsize=(11, 4.4))
    for suite, solver, n in keys:
        sel = sorted((r for r in rows if (r["suite"], r["solver"], r["n"]) == (suite, solver, n)),
                     key=lambda r: r["outlier_ratio"])
        x = [r["outlier_ratio"] for r in sel]
        label = f"{suite}: " * many_suites + f"{solver} (N={n})"
        style = "o-" if len(sel) > 1 else "o"
        ax_s.plot(x, [100 * r["success_rate"] for r in sel], style, label=label)
        ax_t.plot(x, [r["median_time_ms"] for r in sel], style, label=label)
    ax_s.set(xlabel="outlier ratio", ylabel="success rate [%]", ylim=(-5, 105),
             title="success rate")
    ax_t.set(xlabel="outlier ratio", ylabel="median time [ms]", yscale="log",
             title="median time per solve")
    for ax in (ax_s, ax_t):
        ax.grid(True, alpha=0.3)
    if keys:
        ax_t.legend(fontsize=7, loc="best")
    fig.suptitle(title)
    fig.tight_layout()
    written = [out / "bench.png"]
    _savefig(fig, written[0])
    plt.close(fig)

    srows = [r for r in scopes if math.isfinite(r["outlier_ratio"])]
    if srows:
        fig, (ax_c, ax_g) = plt.subplots(1, 2, figsize=(11, 4.4))
        for key in sorted({(r["suite"], r["solver"], r["cert_problem"]) for r in srows}):
            sel = sorted((r for r in srows if (r["suite"], r["solver"], r["cert_problem"]) == key),
                         key=lambda r: r["outlier_ratio"])
            x = [r["outlier_ratio"] for r in sel]
            label = f"{key[0]}: " * many_suites + f"{key[1]} [{key[2]}]"
            style = "o-" if len(sel) > 1 else "o"
            ax_c.plot(x, [100 * r["certified_fraction"] for r in sel], style, label=label)
            ax_g.plot(x, [max(r["median_relative_gap"], 1e-12)
                          if math.isfinite(r["median_relative_gap"]) else np.nan for r in sel],
                      style, label=label)
        ax_c.set(xlabel="outlier ratio", ylabel="certified [%]", ylim=(-5, 105),
                 title="certified fraction per certificate problem")
        ax_g.set(xlabel="outlier ratio", ylabel="median relative gap (floored at 1e-12)",
                 yscale="log", title="duality gap")
        for ax in (ax_c, ax_g):
            ax.grid(True, alpha=0.3)
        ax_g.legend(fontsize=7, loc="best")
        fig.suptitle(title)
        fig.tight_layout()
        written.append(out / "certificates.png")
        _savefig(fig, written[-1])
        plt.close(fig)
    return written


def _savefig(fig: Any, path: Path) -> None:
    from certpose.io.output import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format=path.suffix.lstrip("."))


def _md_num(x: Any, spec: str) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return format(x, spec)


def write_markdown(
    path: str | Path, payload: dict[str, Any], plots: Sequence[Path] = (),
    *, order: Sequence[str] = (),
) -> Path:
    """A Markdown report (``report.md``) to paste into a paper or an issue: the run's setup and
    machine, a table per suite, the certificate table, links to the plots."""
    p = Path(path)
    cfg = payload.get("config", {})
    summary = payload.get("summary", [])
    scopes = payload.get("certificates", [])
    try:
        load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        load = "n/a"
    lines = [
        "# certpose bench report",
        "",
        f"- suites: {', '.join(sorted({r['suite'] for r in summary})) or '-'}",
        f"- solvers: {', '.join(cfg.get('solvers', [])) or '-'}",
        f"- protocol grid: N = {', '.join(map(str, cfg.get('n_values', [])))}; outlier ratios "
        f"{', '.join(f'{r:g}' for r in cfg.get('outlier_ratios', []))}; {cfg.get('trials')} "
        f"trial(s) per cell; sigma = {cfg.get('noise')}; seed {cfg.get('seed')}",
        "- success: protocol suites rotation < 5 deg and translation < 0.05; 3dmatch < 5 deg and "
        "< 0.1 m; eq2 < 10 deg (symmetry axis) and < 2 cm; problem files: their metadata",
        f"- machine: {platform.machine()}, {os.cpu_count()} CPU(s), Python "
        f"{platform.python_version()}; load average when this report was written: {load}",
        f"- rows: `{payload.get('rows', 'trials.csv')}`",
    ]
    run = payload.get("run") or {}
    if run:
        lines.append(f"- run: {_md_num(run.get('wall_seconds'), '.1f')} s wall-clock, workers "
                     f"{run.get('workers')}, {run.get('rows_written')} row(s) written, driver "
                     f"peak RSS {_md_num(run.get('driver_peak_rss_mb'), '.0f')} MiB")
    if payload.get("skipped"):
        lines.append("- skipped: " + "; ".join(f"{k} ({v})" for k, v in payload["skipped"].items()))
    for suite in sorted({r["suite"] for r in summary}):
        lines += ["", f"## {suite}", "",
                  "| solver | N | outliers | trials | success | median rot. err. [deg] | "
                  "median trans. err. | median time [ms] | median TLS cost | certified | "
                  "median gap |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in (r for r in summary if r["suite"] == suite):
            cert = r["certified_fraction"]
            lines.append(
                f"| {r['solver']} | {r['n']} | {_md_num(r['outlier_ratio'], '.2f')} | "
                f"{r['trials']} | {100 * r['success_rate']:.0f}% | "
                f"{_md_num(r['median_rotation_error_deg'], '.3f')} | "
                f"{_md_num(r['median_translation_error'], '.4f')} | "
                f"{_md_num(r['median_time_ms'], '.3f')} | {_md_num(r['median_cost'], '.4g')} | "
                f"{'-' if cert is None or not math.isfinite(cert) else f'{100 * cert:.0f}%'} | "
                f"{_md_num(r['median_relative_gap'], '.2e')} |"
            )
    if scopes:
        lines += ["", "## Certificates", "",
                  "| suite | solver | certificate problem | outliers | certificates | certified | "
                  "median gap | max gap |", "|---|---|---|---:|---:|---:|---:|---:|"]
        for r in scopes:
            lines.append(
                f"| {r['suite']} | {r['solver']} | {r['cert_problem']} | "
                f"{_md_num(r['outlier_ratio'], '.2f')} | {r['certificates']} | "
                f"{100 * r['certified_fraction']:.0f}% | "
                f"{_md_num(r['median_relative_gap'], '.2e')} | "
                f"{_md_num(r['max_relative_gap'], '.2e')} |"
            )
    if plots:
        lines += ["", "## Plots", ""]
        lines += [f"![{q.stem}]({q.name})" for q in plots]
    from certpose.io.output import write_text_atomic

    return write_text_atomic(p, "\n".join(lines) + "\n")
