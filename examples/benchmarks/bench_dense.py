"""Speed of the default solver on dense consistency graphs.

Three measurements of ``certpose.register`` with its default settings (max-clique pruning, then
GNC), each the median of repeated solves of the same problems:

1. the real 3DMatch scan pair in ``../shared/data/3dmatch`` with putative FPFH correspondences
   (:func:`certpose.data.threedmatch.threedmatch_correspondences`, 940 matches, noise bound
   0.05 m): time, success (rotation < 5 deg, translation < 0.1 m), graph edges, tied cliques;
2. sparse and dense consistency graphs of the same size ``--n``: the bunny protocol at 90, 95
   and 98% outliers (outliers in a ball of radius 5: few consistent pairs) against the same
   with the outliers drawn inside the inliers' bounding box (many consistent pairs, >= 130,000
   edges at N = 1000); the worst dense solve over the median sparse one;
3. the bunny protocol at N = 100 for each outlier ratio: median time per solve.

The load average is printed with the figures: the machine is shared.

Usage::

    python examples/benchmarks/bench_dense.py [--repeats 21] [--n 1000] [--trials 50] [--json OUT]
    python examples/benchmarks/bench_dense.py --quick          # a tiny run (the test's)

Measured (2-core machine shared with other sessions, load average 2.8 -> 2.6 over the run;
``--trials 50``, defaults otherwise):

* 3DMatch pair: median 10.1 ms (was 3.2 s at first, 0.73 s here before the
  compiled clique search), 52,696 edges, maximum clique 74 proven, 16 tied cliques solved,
  rotation error 1.25 deg, translation error 0.028 m.
* N = 1000: sparse graphs (1,000-5,900 edges) 3.8-4.3 ms; dense graphs (129,000-139,000 edges)
  10.5 ms at 90% outliers, 17.9 ms at 95%, 55.9 ms (worst 64.0 ms) at 98%, where the exact
  search runs out of its budget (``PruningParams.clique_max_work``): worst dense / median
  sparse 16.7x.
* With the bitset clique search (cores over 256 vertices; 23 November, load average 9-11, two
  runs each, back to back with the tree before it): dense graphs at 98% outliers median 17.0
  and 20.1 ms, worst 17.2 and 27.1 ms (before: median 85.4 and 110.9 ms, worst 120.6 and
  128.8 ms), every maximum clique proven; sparse graphs 2.0-5.8 ms (load); worst dense /
  median sparse 4.7x and 7.5x (before 31x and 44x).
* Bunny N = 100, 0-95% outliers: median 0.27-0.32 ms per solve (0.36-0.43 ms before).
* After the small-solve changes (23 November, quiet, load 0.8-1.1, four runs within ten
  minutes): bunny N = 100 medians 0.222-0.246, 0.170-0.184, 0.266-0.308 and 0.306-0.365 ms
  (the VM's speed phases); interleaved with the code before them, 0.160-0.175 against
  0.183-0.294 ms. 3DMatch pair 6.7-9.4 ms; worst dense / median sparse 6.3-7.1x.
* After the second round (fewer numpy calls per solve: 1.21 M -> 0.81 M instructions per N = 100
  solve, counted with callgrind; 23 November 21:05, quiet, load 0.6-0.7, five runs within a
  minute, and five more at 21:55, load 0.6-1.1): bunny N = 100 medians per outlier ratio
  0.117-0.131 ms in five runs, 0.176-0.244 ms in the other five (the VM's slow phases); the
  median over the ten runs 0.150-0.162 ms at every ratio. Interleaved with the session's start
  (quiet, three rounds): 0.117-0.214 against 0.164-0.303 ms. 3DMatch pair 5.3-10.1 ms; worst
  dense / median sparse 6.7-8.9x.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from certpose.api import register
from certpose.data.instances import make_instance
from certpose.data.threedmatch import (
    NOISE_BOUND,
    default_threedmatch_dir,
    threedmatch_correspondences,
)
from certpose.io.points import load_bunny
from solvers.lie import rotation_error_deg, translation_error

BUNNY = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "bunny" / "bun_zipper_res3.ply"
SIGMA = 0.01


def _median_ms(fn, repeats: int) -> tuple[float, object]:
    out = fn()  # warm (compiled kernels, caches)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3), out


def bench_3dmatch(folder: Path, repeats: int) -> dict:
    corr = threedmatch_correspondences(folder)
    ms, res = _median_ms(
        lambda: register(corr.source, corr.target, noise_bound=NOISE_BOUND), repeats)
    T, G = res.T_target_source, corr.T_target_source
    rot, trans = rotation_error_deg(T[:3, :3], G[:3, :3]), translation_error(T[:3, 3], G[:3, 3])
    return {"n": corr.n, "median_ms": ms, "rotation_error_deg": rot, "translation_error_m": trans,
            "success": bool(res.success and rot < 5 and trans < 0.1), **res.info}


def _dense_instance(shape, n, ratio, rng):
    """The bunny protocol with the outliers drawn inside the inliers' bounding box."""
    inst = make_instance(shape, n, ratio, noise=SIGMA, rng=rng)
    target = inst.target.copy()
    inl = ~inst.outliers
    lo, hi = target[inl].min(axis=0), target[inl].max(axis=0)
    target[inst.outliers] = rng.uniform(lo, hi, size=(int(inst.outliers.sum()), 3))
    return inst, target


def bench_dense_sparse(shape, n: int, ratios, trials: int, repeats: int, rng) -> dict:
    """Median times of sparse and dense graphs of ``n`` vertices per outlier ratio."""
    rows: dict = {}
    for ratio in ratios:
        for kind in ("sparse", "dense"):
            times, edges, ok = [], [], 0
            for _ in range(trials):
                if kind == "sparse":
                    inst = make_instance(shape, n, ratio, noise=SIGMA, rng=rng)
                    target = inst.target
                else:
                    inst, target = _dense_instance(shape, n, ratio, rng)
                ms, res = _median_ms(
                    lambda inst=inst, target=target: register(
                        inst.source, target, noise_bound=inst.noise_bound), repeats)
                T = res.T_target_source
                ok += int(rotation_error_deg(T[:3, :3], inst.rotation) < 5
                          and translation_error(T[:3, 3], inst.translation) < 0.05)
                times.append(ms)
                edges.append(res.info.get("graph_edges", 0))
            rows[f"{kind} {ratio:g}"] = {
                "median_ms": float(np.median(times)), "max_ms": float(np.max(times)),
                "median_edges": float(np.median(edges)), "success_rate": ok / trials}
    sparse = float(np.median([rows[f"sparse {r:g}"]["median_ms"] for r in ratios]))
    rows["sparse_median_ms"] = sparse
    rows["worst_dense_over_sparse"] = max(rows[f"dense {r:g}"]["max_ms"] for r in ratios) / sparse
    return rows


def bench_bunny_small(shape, ratios, trials: int, rng) -> dict:
    out = {}
    for ratio in ratios:
        insts = [make_instance(shape, 100, ratio, noise=SIGMA, rng=rng) for _ in range(trials)]
        register(insts[0].source, insts[0].target, noise_bound=insts[0].noise_bound)
        times, ok = [], 0
        for inst in insts:
            t0 = time.perf_counter()
            res = register(inst.source, inst.target, noise_bound=inst.noise_bound)
            times.append(time.perf_counter() - t0)
            T = res.T_target_source
            ok += int(rotation_error_deg(T[:3, :3], inst.rotation) < 5
                      and translation_error(T[:3, 3], inst.translation) < 0.05)
        out[f"{ratio:g}"] = {"median_ms": float(np.median(times) * 1e3), "success_rate": ok / trials}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=None, help="3DMatch pair folder "
                    "(default ../shared/data/3dmatch)")
    ap.add_argument("--bunny", type=Path, default=BUNNY, help="bunny shape file")
    ap.add_argument("--repeats", type=int, default=21, help="solves per problem (median)")
    ap.add_argument("--n", type=int, default=1000, help="size of the dense/sparse graphs")
    ap.add_argument("--graph-trials", type=int, default=5, help="problems per graph kind")
    ap.add_argument("--graph-ratios", type=float, nargs="+", default=[0.9, 0.95, 0.98],
                    help="outlier ratios of the dense/sparse comparison")
    ap.add_argument("--trials", type=int, default=50, help="bunny N=100 problems per ratio")
    ap.add_argument("--ratios", type=float, nargs="+", default=[0.0, 0.5, 0.8, 0.9, 0.95])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="a tiny run (3 repeats, N = 300, 5 trials)")
    ap.add_argument("--json", type=Path, default=None, help="write the figures as JSON")
    args = ap.parse_args(argv)
    if args.quick:
        args.repeats, args.n, args.graph_trials, args.trials = 3, 300, 1, 5
        args.graph_ratios = [0.9]
    rng = np.random.default_rng(args.seed)
    shape = load_bunny(args.bunny)
    report: dict = {"load_average_before": os.getloadavg()}

    folder = args.data or default_threedmatch_dir()
    m = bench_3dmatch(folder, args.repeats)
    report["3dmatch"] = m
    print(f"3DMatch pair, {m['n']} FPFH correspondences, {m['graph_edges']} edges, max clique "
          f"{m['max_clique_size']} ({m['tied_max_cliques']} tied solved, exact: "
          f"{m['max_clique_exact']}): median {m['median_ms']:.1f} ms over {args.repeats}, "
          f"rotation error {m['rotation_error_deg']:.2f} deg, translation error "
          f"{m['translation_error_m']:.3f} m, success: {m['success']}")

    g = bench_dense_sparse(shape, args.n, args.graph_ratios, args.graph_trials, args.repeats, rng)
    report["graphs"] = g
    for ratio in args.graph_ratios:
        for kind in ("sparse", "dense"):
            r = g[f"{kind} {ratio:g}"]
            print(f"N = {args.n}, {ratio:.0%} outliers, {kind} graph (median "
                  f"{r['median_edges']:.0f} edges): median {r['median_ms']:.2f} ms, worst "
                  f"{r['max_ms']:.2f} ms, success {r['success_rate']:.0%}")
    print(f"worst dense solve / median sparse solve: {g['worst_dense_over_sparse']:.2f}x")

    b = bench_bunny_small(shape, args.ratios, args.trials, rng)
    report["bunny_n100"] = b
    for ratio, r in b.items():
        print(f"bunny N = 100, {float(ratio):.0%} outliers: median {r['median_ms']:.3f} ms per "
              f"solve, success {r['success_rate']:.0%}")
    report["load_average_after"] = os.getloadavg()
    print("load average (1, 5, 15 min) before: {:.2f} {:.2f} {:.2f}, after: {:.2f} {:.2f} {:.2f}"
          .format(*report["load_average_before"], *report["load_average_after"]))
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
