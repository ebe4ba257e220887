"""Certificates on a real scan pair: ``register(certify=True)`` on FPFH correspondences.

The shared 3DMatch pair's correspondences are built as ``certpose bench --suite 3dmatch``
builds them (:func:`certpose.data.threedmatch.threedmatch_correspondences`). Per noise bound
and ``prefer`` option it prints the certificate's problem, verdict, gap and time, the returned
pose's full TLS cost next to GNC's, both poses' errors against the ground truth, and the full
problem's own certificate (recorded in ``info``).

Usage::

    python examples/benchmarks/bench_certify_scans.py [--data DIR] [--noise-bounds 0.05 0.1] [--time-limit 10]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from certpose import register
from certpose.data.threedmatch import threedmatch_correspondences
from solvers.lie import rotation_error_deg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path,
                    default=Path(__file__).resolve().parents[2].parent / "shared" / "data" / "3dmatch")
    ap.add_argument("--noise-bounds", type=float, nargs="+", default=[0.05, 0.1])
    ap.add_argument("--time-limit", type=float, default=10.0)
    args = ap.parse_args()
    corr = threedmatch_correspondences(args.data)
    G = corr.T_target_source
    register(corr.source, corr.target, noise_bound=args.noise_bounds[0])  # compile, untimed
    print(f"{corr.n} correspondences; machine: {os.cpu_count()} cores, load "
          f"{os.getloadavg()[0]:.2f}")
    print(f"{'beta':>5} {'prefer':>11} {'time s':>7} {'certified':>9} {'problem':>24} {'gap':>9} "
          f"{'cost':>8} {'GNC cost':>8} {'rot deg':>7} {'GNC deg':>7} {'full gap':>8}")
    for beta in args.noise_bounds:
        gnc = register(corr.source, corr.target, noise_bound=beta)
        for prefer in ("certificate", "cost"):
            t0 = time.perf_counter()
            res = register(corr.source, corr.target, noise_bound=beta, certify=True,
                           time_limit=args.time_limit, prefer=prefer)
            dt = time.perf_counter() - t0
            c = res.certificate
            full = res.info.get("full_problem_certificate") or (
                c.to_dict() if c.problem == "full_weighted_tls" else {})
            print(f"{beta:5.2f} {prefer:>11} {dt:7.2f} {str(c.certified):>9} {c.problem:>24} "
                  f"{c.relative_gap:9.2e} {res.cost:8.2f} {gnc.cost:8.2f} "
                  f"{rotation_error_deg(res.rotation, G[:3, :3]):7.2f} "
                  f"{rotation_error_deg(gnc.rotation, G[:3, :3]):7.2f} "
                  f"{full.get('relative_gap', float('nan')):8.3f}", flush=True)


if __name__ == "__main__":
    main()
