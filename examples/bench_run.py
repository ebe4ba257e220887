"""A benchmark run: certpose's solvers and peers on the same registration instances.

Usage::

    python examples/bench_run.py [--n 100] [--outlier-ratios 0.5 0.9] [--trials 5] [--workers 0]

The TEASER++/QUASAR protocol on a built-in shape (``N`` points in the unit cube, a random pose,
Gaussian noise on the inliers, outliers uniform in a ball of radius 5), every solver on the same
instances: certpose's default solver and its certified variant, GTSAM's GNC (TLS loss), Open3D's
RANSAC and FGR on the given correspondences. The same as ``certpose bench --n 100
--outlier-ratios 0.5 0.9 --trials 5 --solvers gnc gnc+certify gtsam-gnc o3d-ransac o3d-fgr``;
``--workers N`` runs it on a local Dask cluster of N processes. Needs the ``bench`` extra.
"""

from __future__ import annotations

import argparse

from certpose.bench.report import format_table
from certpose.bench.runner import BenchConfig, run_benchmark

SOLVERS = ("gnc", "gnc+certify", "gtsam-gnc", "o3d-ransac", "o3d-fgr")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100, help="correspondences per instance (default 100)")
    ap.add_argument("--outlier-ratios", type=float, nargs="+", default=[0.5, 0.9])
    ap.add_argument("--trials", type=int, default=5, help="instances per outlier ratio (default 5)")
    ap.add_argument("--solvers", nargs="+", default=list(SOLVERS))
    ap.add_argument("--workers", type=int, default=0, help="Dask worker processes; 0: this process")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    config = BenchConfig(n_values=(args.n,), outlier_ratios=tuple(args.outlier_ratios),
                         trials=args.trials, solvers=tuple(args.solvers), seed=args.seed)
    report = run_benchmark(config, workers=args.workers, progress=False)
    print(format_table(report.summary, report.skipped))
    print(f"{report.run['rows_written']} rows in {report.run['wall_seconds']:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
