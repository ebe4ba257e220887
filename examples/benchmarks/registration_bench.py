"""Run the registration benchmark (bunny, the TEASER++/QUASAR protocol) with every peer.

Usage: ``python examples/benchmarks/registration_bench.py [--out DIR] [--trials-1000 T]``. Writes
``DIR/n100`` and ``DIR/n1000`` (CSV, JSON, PNG) and prints both tables. Needs
``../shared/data/bunny`` beside the repository.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from certpose.cli import main

BUNNY = Path(__file__).resolve().parents[3] / "shared" / "data" / "bunny" / "bun_zipper_res3.ply"


def run() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench-results", help="output folder")
    parser.add_argument("--bunny", default=str(BUNNY), help="bunny PLY path")
    parser.add_argument("--trials-100", type=int, default=20)
    parser.add_argument("--trials-1000", type=int, default=10)
    args = parser.parse_args()
    common = ["bench", "--bunny", args.bunny, "--plot"]
    rc = main([*common, "--n", "100", "--outlier-ratios", "0", "0.5", "0.8", "0.9", "0.95",
               "--trials", str(args.trials_100), "--out", f"{args.out}/n100"])
    rc = rc or main([*common, "--n", "1000", "--outlier-ratios", "0.9", "0.95", "0.99",
                     "--trials", str(args.trials_1000), "--out", f"{args.out}/n1000"])
    return rc


if __name__ == "__main__":
    sys.exit(run())
