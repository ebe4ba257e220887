"""``certpose bench``: certpose's solvers and peers on the same registration instances."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

_DESCRIPTION = """\
Benchmark robust registration on the protocol of the TEASER++/QUASAR papers: N points of a
shape scaled into the unit cube, a random pose, Gaussian noise on inliers, outliers uniform in
a ball of radius 5, noise bound 5.54 sigma. All solvers run side by side on the same
instances. Success: rotation error < 5 deg and translation error < 0.05.

The solves run on Dask: by default a local cluster of one worker process per CPU core
(--workers N sizes it, --workers 0 runs everything in this process, --scheduler ADDRESS uses
a running cluster). With --out, each row (one per instance and solver) is appended to
DIR/trials.csv as it finishes; Ctrl-C or a killed run keeps them, and --resume runs only the
missing ones. An existing result set is never overwritten without --force.
"""


def add_parser(subparsers: Any) -> None:
    from certpose.bench.runner import DEFAULT_SOLVERS, SOLVERS

    p = subparsers.add_parser(
        "bench",
        help="benchmark certpose's registration against GTSAM GNC and Open3D",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--n", type=int, nargs="+", default=[100], metavar="N",
                   help="numbers of correspondences (default: 100)")
    p.add_argument("--outlier-ratios", type=float, nargs="+",
                   default=[0.0, 0.5, 0.8, 0.9, 0.95], metavar="R",
                   help="outlier fractions in [0, 1) (default: 0 0.5 0.8 0.9 0.95)")
    p.add_argument("--noise", type=float, default=0.01, metavar="SIGMA",
                   help="std of the inlier noise, unit-cube units (default: 0.01)")
    p.add_argument("--trials", type=int, default=10, help="instances per cell (default: 10)")
    p.add_argument("--seed", type=int, default=0, help="instance seed (default: 0)")
    p.add_argument("--bunny", metavar="PATH", default=None,
                   help="shape file (e.g. ../shared/data/bunny/bun_zipper_res3.ply), scaled into "
                        "the unit cube; default: the built-in synthetic shape")
    p.add_argument("--solvers", nargs="+", default=list(DEFAULT_SOLVERS), metavar="NAME",
                   choices=list(SOLVERS),
                   help=f"solvers to run, from {{{', '.join(SOLVERS)}}} "
                        f"(default: {' '.join(DEFAULT_SOLVERS)})")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="write summary.csv, trials.csv and bench.json to DIR")
    p.add_argument("--plot", action="store_true",
                   help="also write bench.png (and tightness.png when certificates exist) to --out")
    p.add_argument("--resume", action="store_true",
                   help="keep the rows already in --out and run only the missing ones")
    p.add_argument("--force", action="store_true",
                   help="overwrite the result set already in --out")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="Dask worker processes of the local cluster (default: one per CPU "
                        "core; 0: run in this process, without Dask)")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="send the work to a running Dask scheduler (e.g. tcp://host:8786)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from certpose.bench.runner import BenchConfig, BenchInterrupted, format_table, run_benchmark
    from certpose.cli import CLIError

    if args.plot and args.out is None:
        raise CLIError("--plot needs --out DIR (where to write the PNG files)")
    if (args.resume or args.force) and args.out is None:
        raise CLIError("--resume and --force need --out DIR (the result set)")
    if args.workers is not None and args.workers < 0:
        raise CLIError(f"--workers must be >= 0, got {args.workers}")
    if args.scheduler is not None and args.workers is not None:
        raise CLIError("--scheduler and --workers exclude each other (the cluster is sized "
                       "where it runs)")
    if args.out is not None:
        from certpose.io.output import check_output_dir

        check_output_dir(args.out, what="--out folder")
    config = BenchConfig(
        n_values=tuple(args.n),
        outlier_ratios=tuple(args.outlier_ratios),
        noise=args.noise,
        trials=args.trials,
        seed=args.seed,
        solvers=tuple(args.solvers),
    )
    if args.bunny is not None:
        from certpose.io.points import load_bunny

        shape, shape_name = load_bunny(args.bunny), str(args.bunny)
    else:
        shape, shape_name = None, "synthetic"
    try:
        report = run_benchmark(
            config, shape=shape, shape_name=shape_name, progress=not args.no_progress,
            out_dir=args.out, resume=args.resume, force=args.force, workers=args.workers,
            scheduler=args.scheduler,
        )
    except BenchInterrupted as exc:
        print(f"certpose bench: {exc}", file=sys.stderr)
        return 130
    print(f"shape: {shape_name}; sigma = {config.noise:g}, beta = {config.noise_bound:g}, "
          f"{config.trials} trial(s) per cell, seed {config.seed}")
    print(format_table(report))
    if args.out is not None:
        print(f"wrote {len(report.trials)} row(s) to {Path(args.out) / 'trials.csv'}")
        for path in report.write(args.out, plot=args.plot, trials=False):
            print(f"wrote {path}")
    sys.stdout.flush()
    return 0
