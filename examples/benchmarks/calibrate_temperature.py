"""Fit the importance sampler's temperature scale leave-one-scene-out on the shared YCB-Video
scenes, and score the truth's credible level on the held-out scene.

For every visible (frame, object) pair the MLE runs once (mask classifier, geometry-only model
from ``points.xyz``); the pose distribution is then sampled at each temperature scale of
``--scales`` and the truth's credible level recorded (``PoseDistribution.credible_level``: the
smallest highest-density region that holds the truth; the truth lies in the 90% region when it
is <= 0.9). Rows stream to ``--out`` (JSON lines; ``--resume`` skips pairs already there). The
summary picks, for each held-out scene, the scale whose 90% coverage on the other three scenes is
nearest 0.9 (ties: nearest 0.5 for the 50% region) and reports the held-out scene's coverage at
that scale.

    python examples/benchmarks/calibrate_temperature.py ../shared/data/ycbv --out cal.jsonl
    python examples/benchmarks/calibrate_temperature.py ../shared/data/ycbv --out cal.jsonl --summary
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

SCENES = ("0000", "0002", "0049", "0050")
# BOP's symmetric YCB-V objects: their credible level is not scored.
SYMMETRIC = {"002_master_chef_can", "024_bowl", "036_wood_block", "040_large_marker",
             "051_large_clamp", "052_extra_large_clamp", "061_foam_brick"}


def pairs(root: Path, scenes: list[str], min_px: int) -> list[tuple[str, str]]:
    """Every (frame, object) of ``scenes`` with more than ``min_px`` labelled pixels."""
    from certpose.io.ycbv import load_ycbv_frame

    out = []
    for s in scenes:
        for meta in sorted((root / s).glob("*-meta.mat")):
            frame = f"{s}/{meta.name[:6]}"
            yf = load_ycbv_frame(root, frame)
            for name, index in zip(yf.class_names, yf.class_indexes, strict=True):
                if name in yf.poses and int((yf.label == index).sum()) > min_px:
                    out.append((frame, name))
    return out


def run_pair(root: Path, frame: str, name: str, scales: list[float], resample: int, seed: int) -> dict:
    from certpose.estimation.pipeline import PoseParams, _sample, run_ycbv
    from certpose.geometry.features import FPFHBackbone
    from certpose.io.cache import object_from_points_cached
    from certpose.io.ycbv import load_model_points
    from certpose.sampling import ISParams
    from solvers.lie import invert_transform

    base = PoseParams()
    res = run_ycbv(root, frame, name, params=base, rng=seed)
    G = res.T_camera_object_gt
    obj = object_from_points_cached(load_model_points(root / "models" / name / "points.xyz"),
                                    FPFHBackbone(), voxel_size=base.voxel_size, name=name, rng=0)
    T_cw = invert_transform(res.T_world_camera)
    row = {"frame": frame, "object": name, "symmetric": name in SYMMETRIC,
           "rotation_deg": res.errors.rotation_deg, "add_s_cm": 100 * res.errors.add_s,
           "status": res.status, "levels": {}, "seconds": {}}
    for s in scales:
        p = replace(base, sampler=ISParams(resample=resample, temperature_scale=s))
        t = time.perf_counter()
        dist, info = _sample(res.scene, res.classification, obj, res.mle, T_cw, p,
                             np.random.default_rng(seed))
        row["levels"][str(s)] = float(dist.credible_level(G[:3, :3], G[:3, 3]))
        row["seconds"][str(s)] = time.perf_counter() - t
    return row


def summary(rows: list[dict]) -> None:
    rows = [r for r in rows if not r["symmetric"]]
    scales = sorted({float(s) for r in rows for s in r["levels"]})

    def cover(rs: list[dict], s: float, a: float) -> float:
        return float(np.mean([r["levels"][str(s)] <= a for r in rs])) if rs else float("nan")

    print(f"{len(rows)} non-symmetric pairs; coverage of the 90% / 50% regions per scale:")
    for s in scales:
        print(f"  scale {s:g}: {cover(rows, s, 0.9):.2f} / {cover(rows, s, 0.5):.2f}")
    held = []
    for test in SCENES:
        train = [r for r in rows if not r["frame"].startswith(test)]
        tst = [r for r in rows if r["frame"].startswith(test)]
        if not tst:
            continue
        best = min(scales, key=lambda s: (abs(cover(train, s, 0.9) - 0.9), abs(cover(train, s, 0.5) - 0.5)))
        held += [(r, best) for r in tst]
        print(f"held out {test}: scale {best:g} (train {cover(train, best, 0.9):.2f} / "
              f"{cover(train, best, 0.5):.2f}), test {cover(tst, best, 0.9):.2f} / {cover(tst, best, 0.5):.2f} "
              f"over {len(tst)} pairs")
    if held:
        c90 = np.mean([r["levels"][str(s)] <= 0.9 for r, s in held])
        c50 = np.mean([r["levels"][str(s)] <= 0.5 for r, s in held])
        print(f"leave-one-scene-out: truth in the 90% region {c90:.2f}, in the 50% region {c50:.2f} "
              f"({len(held)} pairs)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", type=Path, help="YCB-Video folder (../shared/data/ycbv)")
    ap.add_argument("--out", type=Path, required=True, help="JSON lines, one per pair")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 2.0, 4.0, 8.0])
    ap.add_argument("--resample", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--min-px", type=int, default=2000)
    ap.add_argument("--resume", action="store_true", help="skip pairs already in --out")
    ap.add_argument("--summary", action="store_true", help="only summarise --out")
    a = ap.parse_args(argv)
    if not a.summary:
        done = set()
        if a.resume and a.out.exists():
            done = {(r["frame"], r["object"]) for r in map(json.loads, a.out.read_text().splitlines())}
        elif a.out.exists():
            sys.exit(f"{a.out} exists: pass --resume to continue it")
        with a.out.open("a") as f:
            for frame, name in pairs(a.root, a.scenes, a.min_px):
                if (frame, name) in done:
                    continue
                row = run_pair(a.root, frame, name, a.scales, a.resample, a.seed)
                f.write(json.dumps(row) + "\n")
                f.flush()
                print(frame, name, {k: round(v, 3) for k, v in row["levels"].items()}, flush=True)
    summary([json.loads(line) for line in a.out.read_text().splitlines()])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
