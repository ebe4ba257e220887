"""Does eq. (2) carry the MLE? Per YCB-Video pair: its inliers at the true pose, its raw pose, and
whether its pose, refined on eq. (1), wins.

For every visible (frame, object) pair of the given scenes (the pairs
``../shared/tools/ycbv_eval.py`` scores: more than ``--min-px`` labelled pixels), with the
geometry-only model (``points.xyz``) and the mask classifier, exactly as ``certpose pose``
builds them, the MLE (:func:`certpose.estimation.mle.estimate_mle`) runs with the eq. (2)
settings given (default: :class:`certpose.model.eq2.Eq2Params`'s: the pairs near the coarse
search's leading hypotheses; ``--num-seeds 0``: the descriptors' top-k, ``--num-object-points``
x ``--top-k``, as the MLE built eq. (2) before; ``--no-mle`` always builds that one). Per pair:

* ``N``: correspondences of eq. (2); ``inliers``: those within the noise bound at the true pose
  (``points``: object points with at least one), i.e. how often the right voxel is among a
  point's ``top_k`` candidates;
* the raw eq. (2) pose (the solver's, or the certifier's when it found a better one): ADD-S and
  rotation error against the truth;
* ``eq2 wins``: the eq. (2) hypothesis, refined on eq. (1), is the MLE's winner, or within
  0.5 cm (translation) and 2 deg of it (and how many nats of eq. (1) it scores below the
  winner: near 0 means another mode as good, e.g. a box's flip);
* solve and certify times (the certifier runs in a thread beside the coarse search), and the
  MLE's total.

The summary line gives the two target fractions: raw ADD-S <= 1 cm in >= 80% of
pairs, eq. (2) wins (or is within 0.5 cm / 2 deg) in >= 80%. ``--no-mle`` only builds, solves
and certifies eq. (2) (faster, for exploring settings).

Usage::

    python examples/benchmarks/bench_eq2.py [--ycbv DIR] [--scenes 0000,0002,0049,0050] [--frames 000001 ...]
        [--objects 025_mug ...] [--num-object-points N] [--top-k K] [--noise-bound M]
        [--num-seeds S] [--gnc-seeds G] [--no-mle] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve()
sys.path.insert(0, str(HERE.parent))

from bench_basins import add_pair_arguments, pairs  # noqa: E402  (the pairs of ycbv_eval)

#: "Within" the winner: translation and rotation of the refined eq. (2) pose from the winner's.
NEAR_TRANSLATION = 0.005
NEAR_ROTATION_DEG = 2.0


def inliers_at(eq2, T: np.ndarray) -> tuple[int, int]:
    """Correspondences of ``eq2`` within its noise bound at pose ``T`` (scene <- object), and
    the object points with at least one."""
    prob = eq2.problem
    ok = prob.residuals_sq(T[:3, :3], T[:3, 3]) <= prob.cbar2
    return int(ok.sum()), int(np.unique(eq2.object_index[ok]).size)


def diagnose(root: Path, frame: str, name: str, params, *, mle: bool = True, seed: int = 0) -> dict:
    from certpose.estimation.mle import estimate_mle
    from certpose.estimation.pipeline import YCBV_SYMMETRY_AXES, pose_errors, ycbv_setup
    from certpose.model.eq2 import build_eq2_problem, certify_eq2, solve_eq2
    from solvers.lie import rotation_error_deg

    # The scene, model and classifier as `certpose pose` builds them.
    setup = ycbv_setup(root, frame, name, params=params)
    yf, points = setup.frame, setup.model_points
    scene, obj, cls = setup.scene, setup.object_model, setup.classification
    T_gt = yf.poses[name]  # camera = scene frame in YCB-Video frames
    axis = YCBV_SYMMETRY_AXES.get(name)
    row: dict = {"case": f"{frame} {name}"}
    if mle:
        t0 = time.perf_counter()
        res = estimate_mle(scene, cls, obj, params=params.mle, likelihood_params=params.likelihood,
                           viewpoint=yf.frame.T_world_camera[:3, 3], rng=seed)
        row["mle_s"] = time.perf_counter() - t0
        eq2, result = res.eq2_problem, res.eq2_result
        row["solve_ms"] = 1e3 * res.timings.get("eq2_solve", math.nan)
        row["certify_ms"] = 1e3 * res.timings.get("eq2_certify", math.nan)
        row["certify_wait_ms"] = 1e3 * res.timings.get("eq2_certify_wait", math.nan)
        row["hypothesis"] = res.hypothesis
        refined = [h for h in res.hypotheses if h.source == "eq2" or h.source.startswith("eq2:")]
        if refined:
            best = max(refined, key=lambda h: h.score)
            d_t = float(np.linalg.norm(best.pose[:3, 3] - res.T_scene_object[:3, 3]))
            d_r = rotation_error_deg(best.pose[:3, :3], res.T_scene_object[:3, :3])
            row.update(eq2_refined_from_winner_cm=100 * d_t, eq2_refined_from_winner_deg=d_r,
                       eq2_refined_nats_below_winner=float(res.log_likelihood - best.score))
            near = d_t <= NEAR_TRANSLATION and d_r <= NEAR_ROTATION_DEG
        else:
            near = False
        row["eq2_wins"] = res.hypothesis.split(":")[0] == "eq2" or near
        err = pose_errors(res.T_scene_object, T_gt, points, symmetry_axis=axis)
        row.update(mle_adds_cm=100 * err.add_s, mle_rot_deg=err.rotation_deg)
    else:
        eq2 = build_eq2_problem(scene, cls, obj, params=params.mle.eq2,
                                likelihood_params=params.likelihood, rng=seed)
        t0 = time.perf_counter()
        result = solve_eq2(eq2, certify=False)
        row["solve_ms"] = 1e3 * (time.perf_counter() - t0)
        t0 = time.perf_counter()
        result = certify_eq2(eq2, result, time_limit=params.mle.certify_time_limit)
        row["certify_ms"] = 1e3 * (time.perf_counter() - t0)
    if eq2 is None or result is None:
        row.update(N=0, inliers=0, points=0, adds_cm=math.nan, rot_deg=math.nan, certified=False)
        return row
    n_in, n_pts = inliers_at(eq2, T_gt)
    err = pose_errors(result.T_target_source, T_gt, points, symmetry_axis=axis)
    cert = result.certificate
    row.update(N=int(eq2.problem.n), inliers=n_in, points=n_pts,
               adds_cm=100 * err.add_s, rot_deg=err.rotation_deg,
               certified=bool(cert is not None and cert.certified),
               gap=None if cert is None else float(cert.relative_gap))
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_pair_arguments(ap)
    ap.add_argument("--num-object-points", type=int, default=None)
    ap.add_argument("--top-k", type=int, default=None)
    ap.add_argument("--noise-bound", type=float, default=None, help="metres (default one voxel)")
    ap.add_argument("--num-seeds", type=int, default=None,
                    help="seed poses of the MLE's eq. (2) (0: the descriptors' top-k, "
                         "--num-object-points x --top-k; default Eq2Params')")
    ap.add_argument("--gnc-seeds", type=int, default=None,
                    help="further seed poses solved with GNC alone (default Eq2Params')")
    ap.add_argument("--no-mle", action="store_true", help="only build, solve and certify eq. (2)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if not args.ycbv.is_dir():
        ap.error(f"--ycbv {args.ycbv} is not a directory")
    from certpose.estimation.pipeline import PoseParams

    params = PoseParams()
    over = {k: v for k, v in (("num_object_points", args.num_object_points),
                              ("top_k", args.top_k), ("noise_bound", args.noise_bound),
                              ("num_seeds", args.num_seeds), ("gnc_seeds", args.gnc_seeds))
            if v is not None}
    eq2p = replace(params.mle.eq2, **over)
    params = replace(params, mle=replace(params.mle, eq2=eq2p))
    how = (f"{eq2p.num_object_points} object points x top-{eq2p.top_k}"
           if eq2p.num_seeds == 0 or args.no_mle else
           f"{eq2p.seed_object_points} object points near {eq2p.num_seeds} seed poses"
           + (f" (+ {eq2p.gnc_seeds} by GNC alone)" if eq2p.gnc_seeds else ""))
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} | eq. (2): "
          f"{how}, noise bound "
          f"{'one voxel' if eq2p.noise_bound is None else f'{eq2p.noise_bound:g} m'}", flush=True)
    rows = []
    for frame, name in pairs(args.ycbv, args.scenes.split(","), args.frames, args.objects,
                             args.min_px):
        row = diagnose(args.ycbv, frame, name, params, mle=not args.no_mle, seed=args.seed)
        rows.append(row)
        line = (f"{row['case']:32s} N {row['N']:5d} inliers@truth {row['inliers']:4d} "
                f"({row['points']:3d} pts) | raw ADD-S {row['adds_cm']:5.2f} cm rot "
                f"{row['rot_deg']:5.1f} deg | solve {row['solve_ms']:6.0f} ms certify "
                f"{row['certify_ms']:6.0f} ms {'certified' if row['certified'] else 'uncertified'}")
        if not args.no_mle:
            line += (f" | MLE {row['mle_s']:5.2f} s ADD-S {row['mle_adds_cm']:5.2f} cm, winner "
                     f"{row['hypothesis']}, eq2 {'wins' if row['eq2_wins'] else 'loses'}")
            if "eq2_refined_from_winner_cm" in row:
                line += (f" ({row['eq2_refined_from_winner_cm']:.2f} cm "
                         f"{row['eq2_refined_from_winner_deg']:.1f} deg, "
                         f"{row['eq2_refined_nats_below_winner']:.1f} nats below it)")
        print(line, flush=True)
        if args.json:
            with args.json.open("a") as f:
                f.write(json.dumps(row) + "\n")
    if rows:
        n = len(rows)
        raw = sum(r["adds_cm"] <= 1.0 for r in rows)
        summary = (f"pairs {n} | raw eq. (2) ADD-S <= 1 cm: {raw}/{n} ({raw / n:.2f}; target "
                   f">= 0.80)")
        if not args.no_mle:
            wins = sum(r["eq2_wins"] for r in rows)
            summary += (f" | refined eq. (2) wins or within 0.5 cm / 2 deg: {wins}/{n} "
                        f"({wins / n:.2f}; target >= 0.80) | median MLE "
                        f"{float(np.median([r['mle_s'] for r in rows])):.2f} s")
        summary += (f" | median N {float(np.median([r['N'] for r in rows])):.0f}, inliers@truth "
                    f"{float(np.median([r['inliers'] for r in rows])):.0f}, solve "
                    f"{float(np.median([r['solve_ms'] for r in rows])):.0f} ms, certify "
                    f"{float(np.median([r['certify_ms'] for r in rows])):.0f} ms | load average "
                    f"{os.getloadavg()[0]:.2f}")
        print(summary)
    return 0 if rows and all(r["N"] > 0 for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
