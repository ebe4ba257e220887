"""Wall time of the ``certpose pose`` program per (frame, object) pair: one call per pair against
one call per frame with all its objects (``--object A B ...``, one process).

For every scene, the objects of the frame whose ground-truth mask holds more than ``--min-px``
pixels (as ``../shared/tools/ycbv_eval.py`` picks them) are posed once by a call of their own and
once by a single call for the whole frame; the rounds alternate which goes first. Each figure is
the wall time of whole processes (interpreter start, imports, reading the frame, the scene, the
object model from its cache, the MLE, printing), so it moves with the machine's load (printed).
The poses of the two ways must be equal: the script checks them (largest difference of the
4x4 ``T_camera_object`` entries).

Target: the MLE in <= 1 s median per frame, <= 2 s including scene building. Measured
quiet 2-core VM (load 1.2-1.3), ``--rounds 2``, frame 000001 of scenes 0000, 0002, 0049,
0050 (18 pairs): one call per pair, median 1.94 s (37.1 s a round); one call per frame, 20.9 s a
round, 1.16 s per pair; the poses of the two ways equal.

load 2.6-4.1 (other sessions' jobs), ``--rounds 1`` twice per tree, alternating,
before and after the scene's FPFH kernels (no open3d import) and the other exact speed-ups of
that day: one call per pair, median 2.70 / 2.57 -> 2.20 / 2.26 s (52.4 / 49.6 -> 42.9 / 41.0 s a
round); one call per frame, 1.65 / 1.66 -> 1.51 / 1.37 s per pair; the poses of the two ways
equal, and equal to those before.

usage::

    python examples/benchmarks/bench_pose_calls.py                        # frame 000001 of the four scenes
    python examples/benchmarks/bench_pose_calls.py --scenes 0000 --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def objects_of(root: Path, frame: str, min_px: int, limit: int | None) -> list[str]:
    """The objects of ``frame`` whose ground-truth mask holds more than ``min_px`` pixels."""
    from certpose.io.ycbv import load_ycbv_frame

    yf = load_ycbv_frame(root, frame)
    names = [n for n in yf.poses if int(yf.object_mask(n).sum()) > min_px]
    return names[:limit] if limit else names


def call(root: Path, frame: str, objects: list[str], out: Path) -> tuple[float, list[np.ndarray]]:
    """Wall seconds of one ``certpose pose`` process and the poses it wrote (one per object)."""
    cmd = [sys.executable, "-m", "certpose", "pose", "--ycbv", str(root), "--frame", frame,
           "--object", *objects, "--json", str(out), "--force", "-q"]  # out: reused per call
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr.strip()[-400:]}")
    payload = json.loads(out.read_text())
    payloads = payload if isinstance(payload, list) else [payload]
    if len(payloads) != len(objects):
        raise SystemExit(f"{frame}: {len(objects)} objects asked for, {len(payloads)} posed")
    return wall, [np.asarray(p["T_camera_object"], dtype=np.float64) for p in payloads]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ycbv", type=Path, default=ROOT.parent / "shared" / "data" / "ycbv")
    ap.add_argument("--scenes", default="0000,0002,0049,0050")
    ap.add_argument("--frame", default="000001", help="the frame of every scene (default 000001)")
    ap.add_argument("--min-px", type=int, default=2000, help="least mask pixels of an object")
    ap.add_argument("--objects", type=int, default=None, metavar="N",
                    help="at most N objects per frame (default: all)")
    ap.add_argument("--rounds", type=int, default=1, help="repetitions, alternating the order")
    args = ap.parse_args()
    if not args.ycbv.is_dir():
        raise SystemExit(f"YCB-Video data not found at {args.ycbv}")
    if args.rounds < 1:
        raise SystemExit(f"--rounds must be >= 1, got {args.rounds}")
    frames = {f"{s}/{args.frame}": objects_of(args.ycbv, f"{s}/{args.frame}", args.min_px, args.objects)
              for s in args.scenes.split(",")}
    n_pairs = sum(len(v) for v in frames.values())
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}; {n_pairs} pairs in "
          f"{len(frames)} frames, {args.rounds} round(s)")
    single: list[float] = []
    batched: list[float] = []  # per round, seconds for all pairs
    worst = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "pose.json"
        for r in range(args.rounds):
            total_batched = 0.0
            for frame, objects in frames.items():
                if not objects:
                    continue
                order = ("single", "batched") if (r % 2 == 0) else ("batched", "single")
                poses: dict[str, list[np.ndarray]] = {}
                for way in order:
                    if way == "single":
                        poses["single"] = []
                        for obj in objects:
                            wall, (T,) = call(args.ycbv, frame, [obj], out)
                            single.append(wall)
                            poses["single"].append(T)
                            print(f"round {r + 1} {frame} {obj:<24} one call   {wall:6.2f} s", flush=True)
                    else:
                        wall, poses["batched"] = call(args.ycbv, frame, objects, out)
                        total_batched += wall
                        print(f"round {r + 1} {frame} {len(objects)} objects{'':<13} one process "
                              f"{wall:6.2f} s ({wall / len(objects):.2f} s per pair)", flush=True)
                diff = max(float(np.abs(a - b).max()) for a, b in zip(poses["single"], poses["batched"],
                                                                      strict=True))
                worst = max(worst, diff)
            batched.append(total_batched)
    print(f"\none call per pair: median {statistics.median(single):.2f} s, "
          f"{sum(single) / args.rounds:.1f} s per round for {n_pairs} pairs")
    print(f"one call per frame: {statistics.median(batched):.1f} s per round, "
          f"{statistics.median(batched) / n_pairs:.2f} s per pair")
    print(f"largest difference of the poses between the two ways: {worst:.2e}; "
          f"load average {os.getloadavg()[0]:.2f}")
    if worst > 1e-9:
        raise SystemExit("the two ways gave different poses")


if __name__ == "__main__":
    main()
