"""Benchmark of the full-problem certificate (clique decomposition) on the bunny protocol.

Measures the certificate's targets, per cell (N, outlier ratio), on ``--reps``
instances (default 18; the TEASER++/QUASAR protocol: bunny in the unit cube, sigma = 0.01,
beta = 5.54 sigma, uniform weights):

* ``cert``: fraction of ``register(certify=True)`` poses certified for the full problem, and the
  median / max certification time (``certificate.solve_time``);
* ``worse``: instances where ``certify=True`` returned a pose of higher full cost than
  ``certify=False`` (must be 0);
* ``1deg``: the certified optimum rotated by 1 deg about a random axis (inliers unchanged) is
  refused (fraction), and the literature's diluted gap of that wrong pose (median);
* with ``--tim``: the TIM rotation-subproblem option (what TEASER++ certifies) on the same
  instances, median time.

Usage::

    python examples/benchmarks/bench_full_certificate.py [--reps 18] [--quick] [--tim] [--out full_cert.png]

Results are printed as a table and plotted (certified fraction and median time per cell).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from certpose import register
from certpose.data.instances import make_instance
from solvers.certify import certify_pose
from solvers.problem import WeightedTLSProblem

SIGMA = 0.01
BETA = 5.54 * SIGMA
CELLS = [(1000, 0.95), (1000, 0.97), (1000, 0.99), (100, 0.8), (100, 0.9), (100, 0.95),
         (100, 0.0), (100, 0.2), (100, 0.5)]


DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "bunny" / "bun_zipper_res3.ply"


def load_bunny() -> np.ndarray:
    from certpose.io import read_points

    pts = read_points(DATA)
    pts = pts - pts.min(axis=0)
    return pts / pts.max()  # into the unit cube


def instance(rng: np.random.Generator, pts: np.ndarray, n: int, ratio: float):  # noqa: ANN201
    inst = make_instance(pts, n, ratio, noise=SIGMA, rng=rng)
    return inst.source, inst.target


def run_cell(pts: np.ndarray, n: int, ratio: float, reps: int, rng: np.random.Generator,
             tim: bool, time_limit: float) -> dict:
    cert, times, worse, refused, litgap, ttim = [], [], 0, [], [], []
    for _ in tqdm(range(reps), desc=f"N={n} {ratio:.0%}", leave=False):
        src, dst = instance(rng, pts, n, ratio)
        p = WeightedTLSProblem(src, dst, noise_bound=BETA)
        plain = register(src, dst, noise_bound=BETA)
        res = register(src, dst, noise_bound=BETA, certify=True, time_limit=time_limit)
        c = res.certificate
        cert.append(c.certified)
        times.append(c.solve_time)
        worse += int(res.cost > plain.cost + 1e-9 * (1 + plain.cost))
        if c.certified:
            ax = rng.normal(size=3)
            Rw = Rotation.from_rotvec(np.radians(1.0) * ax / np.linalg.norm(ax)).as_matrix() @ res.rotation
            if np.array_equal(p.inliers(Rw, res.translation), res.inliers):
                cw = certify_pose(p, Rw, res.translation, time_limit=time_limit)
                refused.append(not cw.certified)
                litgap.append(cw.literature_gap)
        if tim:
            t0 = time.perf_counter()
            register(src, dst, noise_bound=BETA, certify=True, scope="rotation")
            ttim.append(time.perf_counter() - t0)
    return dict(n=n, ratio=ratio, certified=float(np.mean(cert)), median_s=float(np.median(times)),
                max_s=float(np.max(times)), worse=worse,
                refused_1deg=float(np.mean(refused)) if refused else float("nan"),
                n_1deg=len(refused),
                median_literature_gap_1deg=float(np.median(litgap)) if litgap else float("nan"),
                tim_median_s=float(np.median(ttim)) if ttim else float("nan"))


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    for n in sorted({r["n"] for r in rows}):
        sel = sorted((r for r in rows if r["n"] == n), key=lambda r: r["ratio"])
        x = [r["ratio"] for r in sel]
        a1.plot(x, [100 * r["certified"] for r in sel], "o-", label=f"N={n}")
        a2.semilogy(x, [r["median_s"] for r in sel], "o-", label=f"N={n} median")
        a2.semilogy(x, [r["max_s"] for r in sel], "x:", alpha=0.6, label=f"N={n} max")
    a1.axhline(90, color="k", lw=0.8, ls="--", label="target 90%")
    a1.set(xlabel="outlier ratio", ylabel="full problem certified [%]", ylim=(-5, 105))
    a2.set(xlabel="outlier ratio", ylabel="certification time [s]")
    for a in (a1, a2):
        a.legend(fontsize=7)
    fig.suptitle("Full-problem certificates by clique decomposition (bunny protocol)")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    print(f"wrote {out}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=18)
    ap.add_argument("--quick", action="store_true", help="3 instances per cell")
    ap.add_argument("--tim", action="store_true", help="also time the TIM-subproblem option")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--time-limit", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=Path("full_cert.png"))
    args = ap.parse_args()
    reps = 3 if args.quick else args.reps
    rng = np.random.default_rng(args.seed)
    pts = load_bunny()
    # Compile the kernels once, outside the timings.
    src, dst = instance(rng, pts, 30, 0.0)
    register(src, dst, noise_bound=BETA, certify=True)
    print(f"machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; {reps} instances/cell")
    print(f"{'N':>5} {'outl':>5} {'cert':>5} {'med s':>7} {'max s':>7} {'worse':>5} "
          f"{'1deg refused':>12} {'lit gap 1deg':>12} {'TIM med s':>9}")
    rows = []
    for n, ratio in CELLS:
        r = run_cell(pts, n, ratio, reps, rng, args.tim, args.time_limit)
        rows.append(r)
        print(f"{n:5d} {ratio:5.2f} {r['certified']:5.2f} {r['median_s']:7.3f} {r['max_s']:7.3f} "
              f"{r['worse']:5d} {r['refused_1deg']:8.2f}/{r['n_1deg']:<3d} "
              f"{r['median_literature_gap_1deg']:12.2e} {r['tim_median_s']:9.3f}", flush=True)
    plot(rows, args.out)


if __name__ == "__main__":
    main()
