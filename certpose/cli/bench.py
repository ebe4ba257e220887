"""``certpose bench``: certpose's solvers and peers on the same registration instances."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

_DESCRIPTION = """\
Benchmark robust registration: all solvers run side by side on the same instances, from named
suites combinable with a custom grid:

  (default)  the protocol of the TEASER++/QUASAR papers on the built-in shape (or --bunny
             PATH): N points scaled into the unit cube, a random pose, Gaussian noise on
             inliers, outliers uniform in a ball of radius 5, noise bound 5.54 sigma; success:
             rotation error < 5 deg and translation error < 0.05
  bunny      the same protocol on DATA/bunny/bun_zipper_res3.ply, N = 100 and 1000 unless --n
  synthetic  the same protocol on the built-in shape
  3dmatch    the real scan pair DATA/3dmatch with FPFH correspondences and its ground truth
             (success: < 5 deg, < 0.1 m)
  eq2        eq. (2) problems of the pose model: --trials synthetic mug scenes and, when
             DATA/ycbv exists, four YCB-Video frames (success: < 10 deg, < 2 cm)
  --problems DIR   every .npz problem file under DIR (see `certpose register --problem`)

The solves run on Dask: by default a local cluster of one worker process per CPU core
(--workers N sizes it, --workers 0 runs everything in this process, --scheduler ADDRESS uses
a running cluster). With --out, each row (one per instance and solver) is appended to
DIR/trials.csv as it finishes; Ctrl-C or a killed run keeps them, and --resume runs only the
missing ones. An existing result set is never overwritten without --force. The summary,
bench.json, report.md (and with --plot bench.png, certificates.png) are computed from
trials.csv; --report DIR redraws them all from the saved rows without solving.

examples:
  certpose bench --suite bunny --outlier-ratios 0 0.5 0.9 0.95 --trials 20 --out res --plot
  certpose bench --suite 3dmatch eq2 --problems my_problems/ --solvers gnc gnc+certify --out res
  certpose bench --report res
"""


def add_parser(subparsers: Any) -> None:
    from certpose.bench.runner import DEFAULT_SOLVERS, SOLVERS
    from certpose.bench.suites import SUITES
    from certpose.cli import add_common

    p = subparsers.add_parser(
        "bench",
        help="benchmark certpose's registration against its peers on problem suites",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--suite", nargs="+", default=[], metavar="NAME", choices=list(SUITES),
                   help=f"named suites, from {{{', '.join(SUITES)}}} (default: the protocol on "
                        "the built-in shape or --bunny)")
    p.add_argument("--problems", nargs="+", default=[], metavar="DIR",
                   help="folders of .npz problem files, one suite each")
    p.add_argument("--data", metavar="DIR", default=None,
                   help="data folder with bunny/, 3dmatch/, ycbv/ (default: $CERTPOSE_DATA or "
                        "../shared/data)")
    p.add_argument("--n", type=int, nargs="+", default=None, metavar="N",
                   help="numbers of correspondences of the protocol suites (default: 100; "
                        "--suite bunny: 100 1000)")
    p.add_argument("--outlier-ratios", type=float, nargs="+",
                   default=[0.0, 0.5, 0.8, 0.9, 0.95], metavar="R",
                   help="outlier fractions in [0, 1) (default: 0 0.5 0.8 0.9 0.95)")
    p.add_argument("--noise", type=float, default=0.01, metavar="SIGMA",
                   help="std of the inlier noise, unit-cube units (default: 0.01)")
    p.add_argument("--trials", type=int, default=10, help="instances per cell (default: 10)")
    p.add_argument("--bunny", metavar="PATH", default=None,
                   help="shape file (e.g. ../shared/data/bunny/bun_zipper_res3.ply), scaled into "
                        "the unit cube; default: the built-in synthetic shape")
    p.add_argument("--solvers", nargs="+", default=None, metavar="NAME",
                   choices=list(SOLVERS),
                   help=f"solvers to run, from {{{', '.join(SOLVERS)}}} "
                        f"(default: {' '.join(DEFAULT_SOLVERS)}, and teaser++ when "
                        "teaserpp_python is importable)")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="stream trials.csv to DIR, and write summary.csv, bench.json and "
                        "report.md there")
    p.add_argument("--plot", action="store_true",
                   help="also write bench.png (and certificates.png when certificates exist)")
    p.add_argument("--report", metavar="RESULTS_DIR", default=None,
                   help="redraw the summary, JSON, plots and report.md of a result folder from "
                        "its trials.csv, without solving")
    p.add_argument("--resume", action="store_true",
                   help="keep the rows already in --out and run only the missing ones")
    p.add_argument("--force", action="store_true",
                   help="overwrite the result set already in --out")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="Dask worker processes of the local cluster (default: one per CPU "
                        "core; 0: run in this process, without Dask)")
    p.add_argument("--no-dask", action="store_true", help="the same as --workers 0")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="send the work to a running Dask scheduler (e.g. tcp://host:8786)")
    p.add_argument("--batch-size", type=int, default=None, metavar="K",
                   help="protocol instances per Dask task (default: up to 50, fewer towards "
                        "the end so that the workers finish together)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar (shown only when stderr is a terminal)")
    add_common(p, seed_help="instance seed (default: 0)",
               json_help="also write the summary as JSON to OUT ('-': standard output)",
               force=False)
    p.set_defaults(func=run)


def _check(args: argparse.Namespace) -> None:
    from certpose.cli import CLIError

    if args.report is not None:
        other = [o for o, v in (("--suite", args.suite), ("--problems", args.problems),
                                ("--out", args.out), ("--resume", args.resume),
                                ("--force", args.force), ("--scheduler", args.scheduler))
                 if v]
        if other:
            raise CLIError(f"--report redraws saved rows; it takes no {', '.join(other)}")
        return
    if args.plot and args.out is None:
        raise CLIError("--plot needs --out DIR (where to write the PNG files)")
    if (args.resume or args.force) and args.out is None:
        raise CLIError("--resume and --force need --out DIR (the result set)")
    if args.no_dask:
        if args.workers not in (None, 0):
            raise CLIError("--no-dask and --workers N exclude each other")
        args.workers = 0
    if args.workers is not None and args.workers < 0:
        raise CLIError(f"--workers must be >= 0, got {args.workers}")
    if args.scheduler is not None and args.workers is not None:
        raise CLIError("--scheduler and --workers exclude each other (the cluster is sized "
                       "where it runs)")
    if args.batch_size is not None and args.batch_size < 1:
        raise CLIError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.n is not None and min(args.n) < 3:
        raise CLIError(f"--n values must be >= 3, got {' '.join(map(str, args.n))}")
    bad = [r for r in args.outlier_ratios if not (math.isfinite(r) and 0.0 <= r < 1.0)]
    if bad:
        raise CLIError(f"--outlier-ratios must each be in [0, 1), got {' '.join(map(str, bad))} "
                       "(outlier_ratios)")
    if not (math.isfinite(args.noise) and args.noise > 0):
        raise CLIError(f"--noise must be a positive sigma, got {args.noise}")
    if args.trials < 1:
        raise CLIError(f"--trials must be >= 1, got {args.trials}")
    if args.solvers is not None and len(set(args.solvers)) != len(args.solvers):
        raise CLIError(f"--solvers lists a solver twice: {' '.join(args.solvers)}")


def run(args: argparse.Namespace) -> int:
    """The command, holding the lock of its result folder (--out or --report) throughout: a
    second run on the same folder is refused at once, before any work."""
    import contextlib
    import os

    from certpose.io.output import folder_lock

    folder, what = ((args.report, "--report folder") if args.report is not None
                    else (args.out, "--out folder") if args.out is not None else (None, ""))
    if args.report is not None and not os.path.isdir(args.report):
        folder = None  # nothing to lock: the redraw says what is missing
    elif folder is not None and args.report is None:
        from certpose.io.output import check_output_dir

        check_output_dir(folder, what=what)  # before the lock creates it
    # The local cluster's semaphores outlive an interrupted run; the resource tracker (a
    # helper process that takes its warning filters from these options) would report them.
    import sys

    sys.warnoptions.append("ignore:resource_tracker:UserWarning")
    with folder_lock(folder, what=what) if folder is not None else contextlib.nullcontext():
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from certpose.bench.report import format_scopes, format_table
    from certpose.bench.runner import (
        DEFAULT_SOLVERS,
        BenchConfig,
        BenchInterrupted,
        run_benchmark,
        teaser_available,
    )
    from certpose.cli import EXIT_INTERRUPTED, check_json_output, emit_json, say, show_progress

    _check(args)
    check_json_output(args)
    if args.report is not None:
        from certpose.bench.runner import redraw

        report, written = redraw(args.report)
        _print(args, report, format_table, format_scopes)
        for path in written:
            say(args, f"wrote {path}")
        emit_json(args, report.to_dict())
        return 0
    if args.out is not None:
        from certpose.io.output import check_output_dir

        check_output_dir(args.out, what="--out folder")
    solvers = args.solvers
    if solvers is None:
        solvers = list(DEFAULT_SOLVERS) + (["teaser++"] if teaser_available() else [])
    n_values = args.n or ([100, 1000] if "bunny" in args.suite else [100])
    config = BenchConfig(
        n_values=tuple(n_values),
        outlier_ratios=tuple(args.outlier_ratios),
        noise=args.noise,
        trials=args.trials,
        seed=args.seed,
        solvers=tuple(solvers),
        suites=tuple(args.suite),
        problems=tuple(args.problems),
        data_dir=args.data,
    )
    if args.bunny is not None:
        from certpose.io.points import load_bunny

        shape, shape_name = load_bunny(args.bunny), str(args.bunny)
    else:
        shape, shape_name = None, "synthetic"
    try:
        report = run_benchmark(
            # A bar's carriage returns only garble a log: no bar when stderr is not a terminal.
            config, shape=shape, shape_name=shape_name,
            progress=show_progress(args) and sys.stderr.isatty(),
            out_dir=args.out, resume=args.resume, force=args.force, workers=args.workers,
            scheduler=args.scheduler, batch_size=args.batch_size,
        )
    except BenchInterrupted as exc:
        print(f"certpose bench: {exc}", file=sys.stderr)
        return EXIT_INTERRUPTED
    if not config.suites and not config.problems:
        say(args, f"shape: {shape_name}; sigma = {config.noise:g}, beta = "
                  f"{config.noise_bound:g}, {config.trials} trial(s) per cell, seed {config.seed}")
    _print(args, report, format_table, format_scopes)
    if args.out is not None:
        say(args, f"rows: {Path(args.out) / 'trials.csv'}")
        for path in report.write(args.out, plot=args.plot, trials=False):
            say(args, f"wrote {path}")
    emit_json(args, report.to_dict())
    sys.stdout.flush()
    return 0


def _print(args: argparse.Namespace, report: Any, format_table: Any, format_scopes: Any) -> None:
    from certpose.cli import say

    say(args, format_table(report.summary, report.skipped))
    scopes = format_scopes(report.scopes)
    if scopes:
        say(args, "\ncertificates per bounded problem:\n" + scopes)
