"""Certificates on real scan pairs: ``register(certify=True)`` on FPFH correspondences.

The shared 3DMatch pair's correspondences are built as ``certpose bench --suite 3dmatch``
builds them (:func:`certpose.data.threedmatch.threedmatch_correspondences`). Each ``--pair SRC
TGT [GT]`` adds two scans read from point-cloud files, matched as TEASER++'s Python FPFH example
matches them (:func:`certpose.data.threedmatch.scan_correspondences`, voxel ``--voxel-size``,
0.05 m); ``GT`` is a 3DMatch ``gt.log`` (the fragment indices are read from the
``cloud_bin_<k>`` file names) or a file holding the 4x4 ``T_target_source`` (text or ``.npy``).
Without ``GT`` no rotation error is printed (``-``). ``--no-shared`` skips the shared pair.

Per case, noise bound and ``prefer`` option it prints the certificate's problem, verdict, gap
and time, the returned pose's full TLS cost next to GNC's, both poses' errors against the ground
truth, and the full problem's own certificate (recorded in ``info``): its gap and the stages of
the branch and bound over poses that bounded it. With ``--full-time T`` it then runs that branch
and bound alone on GNC's pose for up to ``T`` seconds per noise bound and prints each stage's
target gap, outcome, cells and seconds (what a longer time limit would prove).

Usage::

    python examples/benchmarks/bench_certify_scans.py [--data DIR] [--noise-bounds 0.05 0.1] [--time-limit 10] [--full-time 120]
    python examples/benchmarks/bench_certify_scans.py --pair cloud_bin_0.ply cloud_bin_4.ply gt.log
"""

from __future__ import annotations

import argparse
import os
import re
import time
from pathlib import Path

import numpy as np

from certpose import register
from certpose.data.threedmatch import (
    TEASER_VOXEL_SIZE,
    Correspondences,
    scan_correspondences,
    threedmatch_correspondences,
    threedmatch_log_pose,
)
from solvers.lie import rotation_error_deg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path,
                    default=Path(__file__).resolve().parents[2].parent / "shared" / "data" / "3dmatch")
    ap.add_argument("--no-shared", action="store_true", help="skip the shared 3DMatch pair")
    ap.add_argument("--pair", nargs="+", action="append", default=[], metavar="FILE",
                    help="SRC TGT [GT]: two point-cloud files and an optional ground truth (a "
                         "3DMatch gt.log or a 4x4 T_target_source file); repeatable")
    ap.add_argument("--voxel-size", type=float, default=TEASER_VOXEL_SIZE,
                    help="FPFH voxel in metres for --pair (default: TEASER++'s example's 0.05)")
    ap.add_argument("--noise-bounds", type=float, nargs="+", default=[0.05, 0.1])
    ap.add_argument("--time-limit", type=float, default=10.0)
    ap.add_argument("--full-time", type=float, default=0.0,
                    help="seconds for the full problem's branch and bound alone (0: skip)")
    args = ap.parse_args()
    cases = [] if args.no_shared else [("shared 3DMatch pair", threedmatch_correspondences(args.data))]
    for files in args.pair:
        if len(files) not in (2, 3):
            ap.error(f"--pair takes SRC TGT [GT], got {len(files)} files")
        gt = _ground_truth(*files) if len(files) == 3 else None
        corr = scan_correspondences(files[0], files[1], voxel_size=args.voxel_size,
                                    T_target_source=gt)
        cases.append((f"{Path(files[0]).name} -> {Path(files[1]).name}", corr))
    if not cases:
        ap.error("nothing to run: --no-shared and no --pair")
    _compile_untimed()
    first = cases[0][1]
    register(first.source, first.target, noise_bound=args.noise_bounds[0])  # warm, untimed
    print(f"machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")
    for name, corr in cases:
        _run_case(name, corr, args)
        if args.full_time > 0:
            _full_problem_stages(corr, args.noise_bounds, args.full_time)


def _compile_untimed() -> None:
    """Compile (or load from numba's cache) every kernel the timed calls use, so that a first
    run's compilation (tens of seconds on a fresh install) is not inside their time limits."""
    from solvers.certify import CERTIFY_KERNELS
    from solvers.jit import wait, warm_up
    from solvers.registration import PRUNED_SOLVE_KERNELS

    warm_up((*PRUNED_SOLVE_KERNELS, *CERTIFY_KERNELS, "solvers.certify._kernels",
             "solvers.certify._pose_kernels"))
    wait()


def _ground_truth(source: str, target: str, gt: str) -> np.ndarray:
    """``T_target_source`` from a 3DMatch ``gt.log`` (fragment indices from ``cloud_bin_<k>``
    in the file names) or from a 4x4 matrix file."""
    if gt.endswith(".log"):
        idx = [re.search(r"cloud_bin_(\d+)", Path(f).name) for f in (source, target)]
        if not all(idx):
            raise SystemExit(f"a gt.log needs cloud_bin_<k> file names, got {source}, {target}")
        return threedmatch_log_pose(gt, int(idx[0].group(1)), int(idx[1].group(1)))
    return np.load(gt) if gt.endswith(".npy") else np.loadtxt(gt)


def _run_case(name: str, corr: Correspondences, args: argparse.Namespace) -> None:
    """One case's rows: per noise bound, ``prefer="certificate"`` and ``prefer="cost"``."""
    G = corr.T_target_source
    print(f"== {name}: {corr.n} correspondences (voxel {corr.voxel_size:g} m), ground truth "
          f"{'given' if G is not None else 'none'}; load {os.getloadavg()[0]:.2f}")
    print(f"{'beta':>5} {'prefer':>11} {'time s':>7} {'certified':>9} {'problem':>24} {'gap':>9} "
          f"{'cost':>8} {'GNC cost':>8} {'rot deg':>7} {'GNC deg':>7} {'full gap':>8} "
          f"{'full lit':>8}")

    def err(R: np.ndarray) -> str:
        return f"{'-':>7}" if G is None else f"{rotation_error_deg(R, G[:3, :3]):7.2f}"

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
                  f"{err(res.rotation)} {err(gnc.rotation)} "
                  f"{full.get('relative_gap', float('nan')):8.3f} "
                  f"{full.get('literature_gap', float('nan')):8.2e}", flush=True)
            print(f"      full problem: {full.get('method')}; {full.get('backend_status')}")


def _full_problem_stages(corr, noise_bounds, seconds) -> None:  # noqa: ANN001
    """The full problem's branch and bound over poses alone, on GNC's pose (unit scale, as
    ``register`` certifies)."""
    from solvers.certificate import relative_gap as literature_gap
    from solvers.certificate import undiluted_gap
    from solvers.certify.front import _normalised
    from solvers.certify.pose_bnb import pose_lower_bound
    from solvers.registration import solve_registration, unit_scale_problem

    for beta in noise_bounds:
        unit, _ = unit_scale_problem(corr.source, corr.target, noise_bound=beta, weights=None,
                                     cbar2=1.0)
        pn, _ = _normalised(unit)
        res = solve_registration(pn)
        t0 = time.perf_counter()
        pb = pose_lower_bound(pn, res.rotation, res.translation, tol=1e-3, time_limit=seconds)
        print(f"beta {beta:g}: full problem, {time.perf_counter() - t0:.1f} s, load "
              f"{os.getloadavg()[0]:.2f}: relative gap {pb.proved_gap:.3g}, literature gap "
              f"{literature_gap(pb.upper, pb.lower):.2e} (lower {pb.lower:.3f}, "
              f"upper {pb.upper:.3f}{', a better pose found' if pb.rotation is not None else ''})")
        for gap, done, cells, secs in pb.stages:
            print(f"    target gap {gap:g}: {'proved' if done else 'stopped'}, {cells} cells, "
                  f"{secs:.2f} s")
        Rb, tb = (res.rotation, res.translation) if pb.rotation is None else (pb.rotation,
                                                                              pb.translation)
        c_out = float(pn.cbar2 * pn.weights[pn.residuals_sq(Rb, tb) >= pn.cbar2].sum())
        print("    anytime bound (s: relative gap, literature gap): " + ", ".join(
            f"{sec:.1f}: {undiluted_gap(pb.upper, lo, c_out):.3f}, "
            f"{literature_gap(pb.upper, lo):.1e}" for sec, lo in _thin(pb.curve)))


def _thin(curve, every: float = 2.5):  # noqa: ANN001, ANN202
    """The curve's points at least ``every`` seconds apart, and its last."""
    out, last = [], -np.inf
    for sec, lo in curve:
        if sec - last >= every:
            out.append((sec, lo))
            last = sec
    if curve and (not out or out[-1] != curve[-1]):
        out.append(curve[-1])
    return out


if __name__ == "__main__":
    main()
