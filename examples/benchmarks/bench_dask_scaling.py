"""`certpose bench` at scale: wall time on a local Dask cluster against one process, and the
driver's peak memory as the number of instances grows.

Each configuration is a separate `certpose bench` process on the bunny protocol at N = 100
(outlier ratios 0, 0.5, 0.8, 0.9, 0.95; the trials per cell make up the instance count), with
its rows streamed to a temporary folder; the run reports its own wall time and the driver's
peak RSS (``bench.json``'s ``run``). The ratio is each run's wall time over the ``--workers 0``
run of the same size (cluster start-up included). The machine may be shared: each line also
gives the CPU time of the run's processes (driver, scheduler and workers), the driver's own
(scheduler and row writing included), the CPU time the rest
of the machine used meanwhile (``others_cpu_s``, from ``/proc/stat`` where there is one: a
ratio is only meaningful when it is near zero) and the 1-minute load average at the start.

Usage::

    python examples/benchmarks/bench_dask_scaling.py --instances 1000 10000 --workers 0 2 \\
        --solvers gnc-only
    python examples/benchmarks/bench_dask_scaling.py --instances 1000 --workers 0 2   # default solvers
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

RATIOS = ("0", "0.5", "0.8", "0.9", "0.95")
BUNNY = Path(__file__).resolve().parents[3] / "shared" / "data" / "bunny" / "bun_zipper_res3.ply"


def _bench(instances: int, workers: int, solvers: list[str], shape: str | None,
           batch: int | None, out: Path) -> dict:
    trials = max(1, instances // len(RATIOS))
    cmd = [sys.executable, "-m", "certpose", "bench", "--n", "100", "--outlier-ratios", *RATIOS,
           "--trials", str(trials), "--workers", str(workers), "--out", str(out), "-q",
           "--json", "-"]
    if shape is not None:
        cmd += ["--bunny", shape]
    if solvers:
        cmd += ["--solvers", *solvers]
    if batch is not None:
        cmd += ["--batch-size", str(batch)]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    load = os.getloadavg()[0]
    busy0, cpu0 = _machine_busy(), _children_cpu()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    cpu = _children_cpu() - cpu0  # the workers are reaped by the driver: counted too
    busy = _machine_busy() - busy0
    if proc.returncode != 0:
        raise SystemExit(f"certpose bench failed ({proc.returncode}): {proc.stderr.strip()}")
    data = json.loads(proc.stdout)
    return {"instances": trials * len(RATIOS), **data["run"],
            "solves": sum(r["trials"] for r in data["summary"]), "cpu_s": cpu,
            "others_cpu_s": max(busy - cpu, 0.0), "load": load}


def _children_cpu() -> float:
    import resource

    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _machine_busy() -> float:
    """CPU seconds the whole machine has been busy (NaN without ``/proc/stat``)."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:9]
    except OSError:
        return float("nan")
    ticks = [int(v) for v in fields]
    return (sum(ticks) - ticks[3] - ticks[4]) / os.sysconf("SC_CLK_TCK")  # minus idle, iowait


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--instances", type=int, nargs="+", default=[1000])
    p.add_argument("--workers", type=int, nargs="+", default=[0, 2],
                   help="worker counts; 0 (one process) is the reference of the ratio")
    p.add_argument("--solvers", nargs="*", default=[], help="default: bench's defaults")
    p.add_argument("--batch-size", type=int, default=None)
    p.add_argument("--synthetic", action="store_true",
                   help="the built-in shape instead of the bunny (no data needed)")
    args = p.parse_args()
    shape = None if args.synthetic or not BUNNY.is_file() else str(BUNNY)
    print(f"shape: {shape or 'synthetic'}; solvers: {' '.join(args.solvers) or 'defaults'}; "
          f"{os.cpu_count()} CPU(s); load average before: "
          + ", ".join(f"{v:.2f}" for v in os.getloadavg()))
    print(f"{'instances':>9} {'workers':>7} {'solves':>7} {'wall_s':>8} {'vs_0':>6} "
          f"{'cpu_s':>7} {'driver_cpu_s':>12} {'others_cpu_s':>12} {'load':>5} "
          f"{'driver_peak_MiB':>15}")
    for n in args.instances:
        ref = None
        for w in args.workers:
            with tempfile.TemporaryDirectory() as tmp:
                r = _bench(n, w, args.solvers, shape, args.batch_size, Path(tmp) / "res")
            if w == 0:
                ref = r["wall_seconds"]
            ratio = "-" if ref is None else f"{r['wall_seconds'] / ref:.2f}"
            print(f"{r['instances']:>9} {w:>7} {r['solves']:>7} {r['wall_seconds']:>8.2f} "
                  f"{ratio:>6} {r['cpu_s']:>7.1f} {r['driver_cpu_seconds']:>12.1f} "
                  f"{r['others_cpu_s']:>12.1f} {r['load']:>5.2f} "
                  f"{r['driver_peak_rss_mb']:>15.0f}", flush=True)
    print("load average after: " + ", ".join(f"{v:.2f}" for v in os.getloadavg()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
