"""Benchmark: certification of the FULL weighted TLS problem (rotation and translation).

Bunny protocol of ``examples/benchmarks/bench_certify.py`` (sigma = 0.01, beta = 5.54 sigma, outliers
uniform in a ball of radius 5); the candidate is :func:`solvers.registration.solve_registration`'s
pose. Prints, per K and outlier ratio and per method, the certified fraction, the median relative
gap and the median time:

* ``joint``: :func:`solvers.certify.joint_dual.joint_dual_certificate` (this benchmark's subject);
* ``dual baseline`` (table only): the generic Douglas-Rachford search on the joint lifting that
  ``certify_pose(scope="full", method="dual")`` ran before ``joint``; it lost everywhere and was
  removed from the code, its figures are kept here for the record;
* ``dense``: ``certify_pose(..., scope="full", method="dense")`` (interior point, small K only).

Measured (2-core machine shared with other jobs, load average 3-4, so times are noisy;
3 instances per row, the same instances for both methods; tol 1e-3; "it." = iterations; the
baseline stops at its 3000-iteration cap before some time limits):

====  =====  ==================================  ==================================
K     outl   joint                               dual baseline
             cert  med gap  med t [s]            cert  med gap  med t [s]
====  =====  ==================================  ==================================
10    0.0    1.00  8.6e-04  2.7                  1.00  9.8e-04  3.8
10    0.5    1.00  7.4e-04  10.0                 0.00  1.4e-01  11.1 (3000 it.)
10    0.8    0.00  9.5e-01  37.0 (3000 it.)      0.00  3.4e-01  25.8 (3000 it.)
20    0.0    1.00  9.0e-04  14.7 (510 it.)       1.00  9.9e-04  35.5
20    0.5    1.00  9.6e-04  52.0 (1810 it.)      0.00  1.4e-01  50.3 (3000 it.)
20    0.8    0.00  3.0e-01  60 (limit, 1940 it.) 0.00  1.3e-01  50.1 (3000 it.)
50    0.0    1.00  9.8e-04  203 (1 instance)     0.00  1.0e+00  30 (30 s limit)
====  =====  ==================================  ==================================

Time limits: 60 s for every row except K = 50 (joint 400 s, baseline 30 s) and the K = 10
baseline rows (30 s, all stopped earlier by certification or the iteration cap).

At 80% outliers with K = 10 only two inliers remain, so the rotation about their axis is
free and the optimum is a one-parameter family of poses; a certificate would have to vanish on
all of them, and neither search gets close.

Usage::

    python examples/benchmarks/bench_joint_dual.py [--ks 10 20 50] [--ratios 0 0.5 0.8] [--reps 5]
        [--methods joint dense] [--time-limit 60]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from solvers import solve_registration
from solvers.certificate import relative_gap


def _load_bench_certify():  # noqa: ANN202 - the sibling example module
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parent / "bench_certify.py"
    spec = importlib.util.spec_from_file_location("bench_certify", path)
    mod = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    spec.loader.exec_module(mod)  # type: ignore[union-attr]
    return mod


def run_one(method: str, p, R, t, tol: float, time_limit: float) -> tuple[bool, float, float, int]:  # noqa: ANN001
    """(certified, relative gap, seconds, iterations) of one method on one candidate."""
    t0 = time.perf_counter()
    if method == "joint":
        from threadpoolctl import threadpool_limits

        from solvers.certify.joint_dual import joint_dual_certificate

        with threadpool_limits(1):
            res = joint_dual_certificate(p, R, t, tol=tol, time_limit=time_limit)
        upper = p.cost(R, t)
        gap = relative_gap(upper, res.lower_bound)
        return bool(gap <= tol), float(gap), time.perf_counter() - t0, res.iterations
    import re

    from solvers.certify import certify_pose

    c = certify_pose(p, R, t, scope="full", method=method, tol=tol, time_limit=time_limit)
    m = re.search(r"after (\d+) iterations", c.backend_status)
    its = int(m.group(1)) if m else -1
    return bool(c.certified), float(c.relative_gap), time.perf_counter() - t0, its


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ks", type=int, nargs="+", default=[10, 20, 50])
    ap.add_argument("--ratios", type=float, nargs="+", default=[0.0, 0.5, 0.8])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--methods", nargs="+", default=["joint"])
    ap.add_argument("--time-limit", type=float, default=60.0)
    ap.add_argument("--tol", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    bc = _load_bench_certify()
    bunny = bc.load_bunny()
    print(f"{'method':7s} {'K':>4s} {'outl':>5s} {'cert':>5s} {'med gap':>9s} {'med t[s]':>9s} "
          f"{'max t[s]':>9s} {'med it':>7s}", flush=True)
    for k in args.ks:
        for ratio in args.ratios:
            # The same instances for every method.
            rng = np.random.default_rng([args.seed, k, int(round(100 * ratio))])
            cases = []
            for _ in range(args.reps):
                p, _, _ = bc.instance(rng, bunny, k, ratio)
                res = solve_registration(p)
                cases.append((p, res.rotation, res.translation))
            for method in args.methods:
                out = [run_one(method, p, R, t, args.tol, args.time_limit) for p, R, t in cases]
                cert = np.mean([o[0] for o in out])
                gap = float(np.median([o[1] for o in out]))
                tt = [o[2] for o in out]
                its = int(np.median([o[3] for o in out]))
                print(f"{method:7s} {k:4d} {ratio:5.2f} {cert:5.2f} {gap:9.2e} "
                      f"{np.median(tt):9.3f} {np.max(tt):9.3f} {its:7d}", flush=True)


if __name__ == "__main__":
    main()
