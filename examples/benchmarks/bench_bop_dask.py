"""Wall time of ``certpose pose --bop`` over a whole BOP folder: in process against Dask workers.

Converts the shared YCB-Video frames into a BOP folder (60 targets), builds the object models
into the cache once (``certpose object build --bop``), then runs ``certpose pose --bop`` with
``--workers 0`` (in process) and ``--workers N``, alternating which goes first over the rounds.
Each figure is the wall time of the whole process (start-up, the cluster, every target) and
the CPU seconds of it and its children; the machine's load average is printed before and after
each run, since the figures move with it. The two runs' results must be equal but for the
``time`` column: the script checks them.

usage::

    python examples/benchmarks/bench_bop_dask.py                      # 2 workers, 1 round
    python examples/benchmarks/bench_bop_dask.py --workers 2 --rounds 2
"""

from __future__ import annotations

import argparse
import csv
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def run(ds: Path, out: Path, workers: int) -> tuple[float, float]:
    """Wall and CPU seconds (this process's children) of one ``certpose pose --bop`` run."""
    cmd = [sys.executable, "-m", "certpose", "pose", "--bop", str(ds), "--out", str(out),
           "--workers", str(workers), "--force", "-q"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def rows(path: Path) -> list[tuple[str, ...]]:
    with path.open(newline="") as fh:
        return [tuple(v for k, v in r.items() if k != "time") for r in csv.DictReader(fh)]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "ycbv"))
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--rounds", type=int, default=1)
    args = p.parse_args()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with tempfile.TemporaryDirectory() as tmp:
        ds = Path(tmp) / "ycbv_bop"
        subprocess.run([sys.executable, "-m", "certpose", "bop", "convert-ycbv", args.data,
                        str(ds), "-q"], check=True, env=env)
        subprocess.run([sys.executable, "-m", "certpose", "object", "build", "--bop", str(ds),
                        "-q"], check=True, env=env)
        ratios = []
        for k in range(args.rounds):
            order = [0, args.workers] if k % 2 == 0 else [args.workers, 0]
            res = {}
            for w in order:
                out = Path(tmp) / f"w{w}.csv"
                load0 = _load()
                wall, cpu = run(ds, out, w)
                res[w] = (wall, out)
                print(f"round {k + 1}, --workers {w}: {wall:.1f} s wall, {cpu:.1f} s CPU "
                      f"({cpu / wall:.2f} cores; load {load0} -> {_load()})", flush=True)
            same = rows(res[0][1]) == rows(res[args.workers][1])
            ratios.append(res[args.workers][0] / res[0][0])
            print(f"round {k + 1}: {args.workers} workers / in process = {ratios[-1]:.2f}; "
                  f"results equal but for time: {same}", flush=True)
            if not same:
                return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
