"""Missed basins: eq. (1) at the returned pose against the ground truth refined locally.

For every visible (frame, object) pair of the given YCB-Video scenes (the pairs
``../shared/tools/ycbv_eval.py`` scores: more than ``--min-px`` labelled pixels), with the
geometry-only model (``points.xyz``) and the mask classifier: the MLE pose, and the ground-truth
pose refined locally on the same eq. (1) (:func:`certpose.estimation.mle.refine_pose`). The gap
``eq1(returned) - eq1(refined truth)`` splits the failures in two:

* gap < -1 nat: **the search missed a better basin** (the likelihood prefers the truth's basin,
  the returned pose is worse): the target is gap >= -1 in >= 95% of pairs;
* gap >= -1 with a large error: **the likelihood prefers the wrong pose** (a model problem, e.g.
  a box's flips without appearance).

Usage::

    python examples/benchmarks/bench_basins.py [--ycbv DIR] [--scenes 0000,0002,0049,0050]
                                    [--frames 000001 ...] [--objects 024_bowl ...] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve()
#: BOP's symmetric YCB-V objects (as ``../shared/tools/ycbv_eval.py``): no flip to report.
SYMMETRIC = {"002_master_chef_can", "024_bowl", "036_wood_block", "040_large_marker",
             "051_large_clamp", "052_extra_large_clamp", "061_foam_brick"}


def pairs(root: Path, scenes: list[str], frames: list[str] | None, objects: list[str] | None,
          min_px: int):
    """``(scene/frame, object)`` with more than ``min_px`` labelled pixels, in file order."""
    from certpose.io.ycbv import load_ycbv_frame

    for scene in scenes:
        for meta in sorted((root / scene).glob("*-meta.mat")):
            fr = meta.name[:6]
            if frames and fr not in frames:
                continue
            yf = load_ycbv_frame(root, f"{scene}/{fr}")
            for name in yf.poses:
                if objects and name not in objects:
                    continue
                if int(yf.object_mask(name).sum()) > min_px:
                    yield f"{scene}/{fr}", name


def diagnose(root: Path, frame: str, name: str, *, seed: int = 0, free_space: str | None = None,
             field_blur: float | None = None) -> dict:
    from certpose.estimation.mle import estimate_mle, refine_pose
    from certpose.estimation.pipeline import (
        YCBV_SYMMETRY_AXES,
        PoseParams,
        pose_errors,
        ycbv_setup,
    )
    from certpose.model.likelihood import LikelihoodParams, PoseLikelihood

    params = PoseParams()
    if free_space is not None:
        params = replace(params, likelihood=replace(params.likelihood, free_space=free_space))
    if field_blur is not None:
        params = replace(params, likelihood=replace(params.likelihood, field_blur=field_blur))
    # The scene, model and classifier exactly as `certpose pose` builds them.
    setup = ycbv_setup(root, frame, name, params=params)
    yf, points = setup.frame, setup.model_points
    scene, obj, cls = setup.scene, setup.object_model, setup.classification
    lik = PoseLikelihood(scene, cls, obj, params=params.likelihood or LikelihoodParams())
    t0 = time.perf_counter()
    mle = estimate_mle(scene, cls, obj, params=params.mle, likelihood_params=params.likelihood,
                       viewpoint=yf.frame.T_world_camera[:3, 3], rng=seed)
    seconds = time.perf_counter() - t0
    T_gt = yf.poses[name]  # camera = world frame in YCB-Video frames
    T_ref, ll_ref, _ = refine_pose(lik, T_gt, scale=obj.radius)
    ll_ret = float(lik.log_likelihood(mle.T_scene_object))
    axis = YCBV_SYMMETRY_AXES.get(name)
    err = pose_errors(mle.T_scene_object, T_gt, points, symmetry_axis=axis).to_dict()
    err_ref = pose_errors(T_ref, T_gt, points, symmetry_axis=axis).to_dict()
    gap = ll_ret - float(ll_ref)
    # The geometry-only target: where a flip ties, the truth is among the reported modes.
    mode_err = [pose_errors(m.T_scene_object, T_gt, points, symmetry_axis=axis).to_dict()
                for m in mle.modes] or [err]
    k = int(np.argmin([e["rotation_deg"] for e in mode_err]))
    return {
        "case": f"{frame} {name}", "eq1_returned": ll_ret, "eq1_truth": float(lik.log_likelihood(T_gt)),
        "eq1_truth_refined": float(ll_ref), "gap": gap,
        "verdict": "missed basin" if gap < -1.0 else "ok",
        "hypothesis": mle.hypothesis, "mle_s": seconds,
        "adds_cm": 100 * err["add_s"], "rot_deg": err["rotation_deg"],
        "refined_truth_adds_cm": 100 * err_ref["add_s"],
        "refined_truth_rot_deg": err_ref["rotation_deg"],
        "symmetric": name in SYMMETRIC, "modes": len(mle.modes),
        "mode_window": float(params.mle.mode_window),
        "truth_mode_rot_deg": mode_err[k]["rotation_deg"],
        "truth_mode_adds_cm": 100 * mode_err[k]["add_s"],
        "truth_in_modes": bool(mode_err[k]["rotation_deg"] <= 10.0 and mode_err[k]["add_s"] <= 0.01),
    }


def add_pair_arguments(ap: argparse.ArgumentParser) -> None:
    """The options that choose the YCB-Video pairs (see :func:`pairs`) and the JSON output."""
    ap.add_argument("--ycbv", type=Path, default=HERE.parents[3] / "shared" / "data" / "ycbv")
    ap.add_argument("--scenes", default="0000,0002,0049,0050")
    ap.add_argument("--frames", nargs="+", default=None)
    ap.add_argument("--objects", nargs="+", default=None)
    ap.add_argument("--min-px", type=int, default=2000)
    ap.add_argument("--json", type=Path, default=None, help="append one JSON line per pair")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_pair_arguments(ap)
    ap.add_argument("--free-space", choices=("voxels", "pixels"), default=None,
                    help="LikelihoodParams.free_space (default: the library's)")
    ap.add_argument("--field-blur", type=float, default=None, metavar="M",
                    help="LikelihoodParams.field_blur (metres; default: the library's)")
    args = ap.parse_args(argv)
    if not args.ycbv.is_dir():
        ap.error(f"--ycbv {args.ycbv} is not a directory")
    rows = []
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}, free space "
          f"{args.free_space or 'default'}, field blur "
          f"{'default' if args.field_blur is None else args.field_blur}")
    for frame, name in pairs(args.ycbv, args.scenes.split(","), args.frames, args.objects,
                             args.min_px):
        row = diagnose(args.ycbv, frame, name, free_space=args.free_space, field_blur=args.field_blur)
        rows.append(row)
        print(f"{row['case']:32s} gap {row['gap']:+9.1f} nats ({row['verdict']:12s}) "
              f"ADD-S {row['adds_cm']:6.2f} cm rot {row['rot_deg']:6.1f} deg | refined truth "
              f"ADD-S {row['refined_truth_adds_cm']:5.2f} cm | {row['hypothesis']} | {row['modes']} "
              f"mode(s), nearest the truth {row['truth_mode_rot_deg']:.0f} deg", flush=True)
        if args.json:
            with args.json.open("a") as f:
                f.write(json.dumps(row) + "\n")
    if rows:
        ok = sum(r["gap"] >= -1.0 for r in rows)
        print(f"pairs {len(rows)} | returned eq. (1) >= refined truth - 1 nat: {ok}/{len(rows)} "
              f"({ok / len(rows):.2f}; target >= 0.95) | median MLE "
              f"{float(np.median([r['mle_s'] for r in rows])):.2f} s")
        # Non-symmetric pairs returned flipped (more than 150 deg off, as ycbv_eval counts flips)
        # whose refined truth is within the mode window of the returned pose (a tie): is the
        # truth among the reported modes?
        wrong = [r for r in rows if not r["symmetric"] and r["rot_deg"] > 150.0]
        ties = [r for r in wrong if r["gap"] <= r["mode_window"]]
        found = sum(r["truth_in_modes"] for r in ties)
        print(f"non-symmetric pairs flipped (> 150 deg): {len(wrong)}; of them ties (refined truth "
              f"within the {rows[0]['mode_window']:g}-nat mode window): {len(ties)}, truth among "
              f"the reported modes in {found}/{len(ties)}; off by more than the window: "
              f"{len(wrong) - len(ties)}")
    return 0 if all(math.isfinite(r["gap"]) for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
