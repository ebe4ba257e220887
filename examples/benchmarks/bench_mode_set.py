"""Eq. (2)'s certified mode set: on the demo and on the 60 shared YCB-Video pairs, in how many is
it certified within its time limit, and what does it list.

For the demo (``certpose pose --demo``) and every visible (frame, object) pair of the given
YCB-Video scenes (the pairs ``../shared/tools/ycbv_eval.py`` scores: more than ``--min-px``
labelled pixels; geometry-only model, mask classifier), the pose pipeline runs with
``PoseParams.mode_set`` (margin 2% of the best eq. (2) cost, 10 s), on the eq. (2) problem
whose minimiser the pipeline certifies, seeded by that minimiser, the returned pose and the
modes. Per case: the status, the seconds, the regions (rotation radius, translation
half-width), the boxes bounded, and the literature gap of the minimiser (the larger of the
mode set's lower bound and the eq. (2) certificate's). The machine's load is printed at the
start and the end: the time limit is wall-clock.

``--save DIR`` keeps each case's eq. (2) problem and seeds (``<case>.npz``); ``--problems DIR``
runs the mode set alone on saved ones (no pipeline), e.g. to compare options.

Usage::

    python examples/benchmarks/bench_mode_set.py [--ycbv DIR] [--time-limit 10] [--margin 0.02]
        [--no-demo] [--scenes 0000,0002,0049,0050] [--save DIR] [--json OUT]
    python examples/benchmarks/bench_mode_set.py --problems DIR [--time-limit 10]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve()
sys.path.insert(0, str(HERE.parent))

from bench_basins import add_pair_arguments, pairs  # noqa: E402  (the pairs of ycbv_eval)


def summarise(case: str, ms, cert_lower: float, seconds: float) -> dict:
    """One JSON row of a mode-set result (``cert_lower``: the eq. (2) certificate's bound)."""
    from solvers.certificate import relative_gap

    lower = max(ms.lower_bound, cert_lower) if math.isfinite(cert_lower) else ms.lower_bound
    return {"case": case, "status": ms.status.value, "certified": bool(ms.success),
            "mode_set_s": round(ms.solve_time, 3), "pipeline_s": round(seconds, 2),
            "regions": [[round(math.degrees(r.rotation_radius), 2),
                         round(100 * r.translation_half_width, 3)] for r in ms.regions],
            "best": ms.best_cost, "margin": ms.margin, "boxes": ms.boxes_explored,
            "mode_set_lower": ms.lower_bound, "certificate_lower": cert_lower,
            "gap": relative_gap(ms.best_cost, lower), "load": round(os.getloadavg()[0], 2)}


def show(row: dict) -> None:
    regs = ", ".join(f"{a:.1f} deg x {t:.2f} cm" for a, t in row["regions"]) or "-"
    print(f"{row['case']:34s} {row['status']:11s} {row['mode_set_s']:6.2f} s  "
          f"{len(row['regions'])} region(s) [{regs}]  gap {row['gap']:.3g}  "
          f"{row['boxes']} boxes  load {row['load']:.1f}", flush=True)


def run_case(case: str, result, save: Path | None) -> dict:
    ms = result.mode_set
    cert = result.certificate
    cert_lower = float(cert.lower_bound) if cert is not None else float("nan")
    if save is not None and result.mle is not None and result.mle.eq2_problem is not None:
        p = result.mle.eq2_problem.problem
        m = result.mle
        seeds = np.stack([m.eq2_result.T_target_source, m.T_scene_object,
                          *(x.T_scene_object for x in m.modes)])
        save.mkdir(parents=True, exist_ok=True)
        np.savez(save / (case.replace("/", "_").replace(" ", "_") + ".npz"), source=p.source,
                 target=p.target, weights=p.weights, noise_bound=p.noise_bound, seeds=seeds,
                 certificate_lower=cert_lower)
    return summarise(case, ms, cert_lower, result.timings.get("mle", float("nan"))
                     + result.timings.get("mode_set", 0.0))


def from_problems(folder: Path, params) -> list[dict]:
    from solvers import WeightedTLSProblem
    from solvers.certify.mode_set import certify_mode_set

    rows = []
    for f in sorted(folder.glob("*.npz")):
        d = np.load(f)
        p = WeightedTLSProblem(d["source"], d["target"], noise_bound=d["noise_bound"],
                               weights=d["weights"])
        ms = certify_mode_set(p, d["seeds"], params=params)
        rows.append(summarise(f.stem, ms, float(d["certificate_lower"]), ms.solve_time))
        show(rows[-1])
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_pair_arguments(ap)
    ap.add_argument("--time-limit", type=float, default=10.0)
    ap.add_argument("--margin", type=float, default=0.02)
    ap.add_argument("--no-demo", action="store_true")
    ap.add_argument("--save", type=Path, default=None)
    ap.add_argument("--problems", type=Path, default=None)
    args = ap.parse_args(argv)
    from dataclasses import replace

    from certpose.estimation.pipeline import PoseParams, run_demo, run_ycbv
    from solvers.certify.mode_set import ModeSetParams

    msp = ModeSetParams(margin=args.margin, time_limit=args.time_limit)
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} at the start; margin "
          f"{args.margin:g}, time limit {args.time_limit:g} s", flush=True)
    if args.problems is not None:
        rows = from_problems(args.problems, msp)
    else:
        params = replace(PoseParams(), mode_set=msp)
        rows = []
        todo = [] if args.no_demo else [("demo", None)]
        if args.ycbv.is_dir():
            todo += list(pairs(args.ycbv, args.scenes.split(","), args.frames, args.objects,
                               args.min_px))
        for frame, name in todo:
            t0 = time.perf_counter()
            if name is None:
                result = run_demo(params=params, rng=0)
                case = "demo"
            else:
                result = run_ycbv(args.ycbv, frame, name, params=params, rng=0)
                case = f"{frame} {name}"
            if result.mode_set is None:
                print(f"{case}: no eq. (2) problem ({result.message})", flush=True)
                continue
            row = run_case(case, result, args.save)
            row["wall_s"] = round(time.perf_counter() - t0, 2)
            rows.append(row)
            show(row)
            if args.json:
                with args.json.open("a") as f:
                    f.write(json.dumps(row) + "\n")
    if rows:
        ok = sum(r["certified"] for r in rows)
        times = [r["mode_set_s"] for r in rows]
        print(f"cases {len(rows)} | mode set certified {ok}/{len(rows)} ({ok / len(rows):.2f}; "
              f"target >= 0.80) within {args.time_limit:g} s | median {np.median(times):.2f} s, "
              f"max {max(times):.2f} s | median gap {np.median([r['gap'] for r in rows]):.3g} | "
              f"load average {os.getloadavg()[0]:.2f} at the end", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
