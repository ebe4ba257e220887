"""Calibration of the pose distribution on the shared YCB-Video frames (issue #11).

For every visible (frame, object) pair of the given scenes, with the frame's ground-truth mask
as the classifier, the MLE is found once, then the importance sampler is run at each
``--scales`` multiple of the default temperature rule
(:func:`certpose.sampling.sampler.default_temperature`). For each run the ground-truth pose's
highest-density credible level (:meth:`PoseDistribution.credible_level`) is recorded: the
truth lies inside the 90% (50%) credible region when its level is <= 0.9 (0.5). A calibrated
distribution puts it inside the 90% region in 80-100% of pairs and inside the 50% region in
35-65% (the issue's target). Models: geometry-only (``points.xyz``) on every pair, and, with
``--appearance``, appearance models built from the views of the *other* scene for the objects
seen in two scenes (never evaluated on the scene whose views built them).

Symmetric objects (BOP's YCB-V list) have no single true pose: their level is taken at the
best of the ground truth's equivalents under rotations about the model's z axis (every 10 deg)
and a half turn about x (stated, lenient), and they are reported apart. A run whose effective
sample size is below ``MIN_ESS`` has no meaningful level and counts as outside.

usage::

    python examples/bench_calibration.py                          # 4 scenes, geometry models
    python examples/bench_calibration.py --appearance --scales 0.5 1 2 4 --out calib.jsonl
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

SYMMETRIC = {"002_master_chef_can", "024_bowl", "036_wood_block", "040_large_marker",
             "051_large_clamp", "052_extra_large_clamp", "061_foam_brick"}
#: Objects seen in two scenes: an appearance model from one is tested on the other.
OTHER_SCENE = {("006_mustard_bottle", "0002"): "0050", ("006_mustard_bottle", "0050"): "0002",
               ("011_banana", "0002"): "0050", ("011_banana", "0050"): "0002",
               ("010_potted_meat_can", "0002"): "0049", ("010_potted_meat_can", "0049"): "0002"}


def _equivalents(T_gt: np.ndarray, symmetric: bool) -> list[np.ndarray]:
    from scipy.spatial.transform import Rotation

    if not symmetric:
        return [T_gt]
    out = []
    for flip in (np.eye(3), Rotation.from_rotvec([np.pi, 0, 0]).as_matrix()):
        for a in np.radians(np.arange(0, 360, 10)):
            T = T_gt.copy()
            T[:3, :3] = T_gt[:3, :3] @ Rotation.from_rotvec([0, 0, a]).as_matrix() @ flip
            out.append(T)
    return out


def _frames(root: Path, scene: str) -> list[str]:
    return sorted(f"{scene}/{p.name[:6]}" for p in (root / scene).glob("*-meta.mat"))


def run_pair(root: Path, frame: str, obj: str, scales: list[float], draws: int,
             object_model=None) -> dict:  # noqa: ANN001
    from certpose.estimation.mle import estimate_mle
    from certpose.estimation.pipeline import PoseParams
    from certpose.geometry.features import FPFHBackbone
    from certpose.geometry.objects import object_from_points
    from certpose.io.ycbv import load_model_points, load_ycbv_frame
    from certpose.model.classifier import classify_from_mask
    from certpose.model.likelihood import PoseLikelihood
    from certpose.model.scene import build_scene_field
    from certpose.sampling.sampler import (
        ISParams,
        default_temperature,
        sample_pose_distribution,
        seeds_from_mle,
    )

    params = PoseParams()
    yf = load_ycbv_frame(root, frame)
    mask = yf.object_mask(obj)
    backbone = object_model.backbone if object_model is not None else FPFHBackbone()
    scene = build_scene_field(yf.frame, backbone, voxel_size=params.voxel_size, roi_mask=mask,
                              margin=params.roi_margin)
    if object_model is not None:
        model = object_model.model
    else:
        model = object_from_points(load_model_points(root / "models" / obj / "points.xyz"),
                                   backbone, voxel_size=params.voxel_size, name=obj)
    cls = classify_from_mask(scene, yf.frame.with_mask(mask), params=params.classifier)
    t = time.perf_counter()
    mle = estimate_mle(scene, cls, model, params=params.mle, likelihood_params=params.likelihood,
                       viewpoint=np.zeros(3), rng=0)
    t_mle = time.perf_counter() - t
    lik = PoseLikelihood(scene, cls, model, params=params.likelihood)
    T_gt = yf.poses[obj]  # scene frame = camera frame for YCB-Video frames
    R_err = np.degrees(np.arccos(np.clip((np.trace(T_gt[:3, :3].T @ mle.T_scene_object[:3, :3]) - 1)
                                         / 2, -1, 1)))
    row = {"case": f"{frame} {obj}", "object": obj, "symmetric": obj in SYMMETRIC,
           "model": "appearance" if object_model is not None else "geometry",
           "mle_rot_err_deg": round(float(R_err), 2),
           "mle_trans_err_cm": round(float(100 * np.linalg.norm(mle.T_scene_object[:3, 3]
                                                                 - T_gt[:3, 3])), 3),
           "mle_s": round(t_mle, 2),
           "default_temperature": round(default_temperature(lik, mle.T_scene_object), 3),
           "gt_minus_mle_nats": round(float(lik(T_gt[None])[0] - mle.log_likelihood), 2),
           "levels": {}, "ess": {}, "sampling_s": {}}
    seeds = seeds_from_mle(mle)
    eqs = _equivalents(T_gt, obj in SYMMETRIC)
    for s in scales:
        res = sample_pose_distribution(lik, seeds, params=ISParams(draws=draws, temperature_scale=s,
                                                                   resample=0), rng=0)
        d = res.weighted
        level = min(d.credible_level(T[:3, :3], T[:3, 3], max_particles=draws) for T in eqs)
        row["levels"][str(s)] = round(level, 4)
        row["ess"][str(s)] = round(d.ess, 1)
        row["sampling_s"][str(s)] = round(res.seconds, 2)
    return row


#: Below this ESS a run's level means nothing (one particle carries the mass): counted outside.
MIN_ESS = 50.0


def _level(row: dict, s: float) -> float:
    return row["levels"][str(s)] if row["ess"][str(s)] >= MIN_ESS else 1.0


def summarise(rows: list[dict], scales: list[float]) -> None:
    print(f"\n{'pairs':<34} {'scale':>6} {'in 90%':>8} {'in 50%':>8} {'median level':>13} "
          f"{'ESS<' + str(int(MIN_ESS)):>8}")
    groups = {
        "non-symmetric, geometry": [r for r in rows if not r["symmetric"] and r["model"] == "geometry"],
        "non-symmetric, appearance": [r for r in rows if not r["symmetric"] and r["model"] == "appearance"],
        "symmetric (best equivalent)": [r for r in rows if r["symmetric"]],
        "all": rows,
    }
    for name, rs in groups.items():
        if not rs:
            continue
        for s in scales:
            lv = np.array([_level(r, s) for r in rs])
            low = sum(r["ess"][str(s)] < MIN_ESS for r in rs)
            print(f"{name + f' ({len(rs)})':<34} {s:>6g} {np.mean(lv <= 0.9):>8.2f} "
                  f"{np.mean(lv <= 0.5):>8.2f} {np.median(lv):>13.3f} {low:>8d}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    here = Path(__file__).resolve().parents[1]
    ap.add_argument("--data", type=Path, default=here.parent / "shared" / "data" / "ycbv")
    ap.add_argument("--scenes", default="0000,0002,0049,0050")
    ap.add_argument("--frames", default="", help="comma-separated frame numbers to keep (e.g. 000001)")
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 2.0, 4.0])
    ap.add_argument("--draws", type=int, default=3000)
    ap.add_argument("--appearance", action="store_true",
                    help="also appearance models from the other scene's views")
    ap.add_argument("--min-px", type=int, default=2000)
    ap.add_argument("--out", type=Path, default=None, help="append one JSON line per pair")
    ap.add_argument("--summarise", type=Path, default=None, metavar="JSONL",
                    help="only print the summary of the rows of an earlier --out file")
    args = ap.parse_args()
    if args.summarise is not None:
        rows = [json.loads(line) for line in args.summarise.read_text().splitlines() if line.strip()]
        summarise(rows, args.scales)
        return
    if not args.data.is_dir():
        raise SystemExit(f"YCB-Video folder not found: {args.data}")
    from certpose.estimation.pipeline import build_ycbv_object_model
    from certpose.io.ycbv import load_ycbv_frame

    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}; scales {args.scales}, "
          f"{args.draws} draws")
    keep = set(filter(None, args.frames.split(",")))
    rows, models = [], {}
    for scene in args.scenes.split(","):
        for frame in _frames(args.data, scene):
            if keep and frame.split("/")[1] not in keep:
                continue
            yf = load_ycbv_frame(args.data, frame)
            for obj in sorted(yf.poses):
                try:
                    if yf.object_mask(obj).sum() <= args.min_px:
                        continue
                except (KeyError, ValueError):
                    continue
                jobs = [None]
                other = OTHER_SCENE.get((obj, scene))
                if args.appearance and other is not None:
                    if (obj, other) not in models:
                        models[(obj, other)] = build_ycbv_object_model(
                            args.data, _frames(args.data, other), obj)
                    jobs.append(models[(obj, other)])
                for om in jobs:
                    row = run_pair(args.data, frame, obj, args.scales, args.draws, om)
                    rows.append(row)
                    print(json.dumps(row), flush=True)
                    if args.out is not None:
                        with open(args.out, "a") as fh:
                            fh.write(json.dumps(row) + "\n")
    summarise(rows, args.scales)


if __name__ == "__main__":
    main()
