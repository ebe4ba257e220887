"""Time of the maximum-likelihood estimate (``estimate_mle``) per (frame, object) pair, warm, in one
process, split by stage.

The pairs are those ``certpose pose --ycbv`` poses in ``../shared/tools/ycbv_eval.py``: the objects
of the frame whose ground-truth mask holds more than ``--min-px`` pixels. Each pair is built as
``certpose pose --ycbv`` builds it (scene field around the mask, the geometry-only model from
``models/<object>/points.xyz`` through the model cache, the mask classifier, the CLI's default
parameters and seed) before any timing; then ``estimate_mle`` runs on every pair ``--rounds``
times. The first round only warms (compiled kernels, cached visibility tables and axes of
revolution) unless ``--rounds 1``; the figure per pair is the median of the other rounds.

The stages are the keys of ``MLEResult.timings`` (``coarse_search``, ``eq2_solve``, ``refine``,
``hop``, ``modes``, ``polish``, ...). The certifier runs in a thread beside the search: its time
(``eq2_certify``) overlaps the others and only ``eq2_certify_wait`` adds to the total.

Target: median <= 1 s per pair on the project's 2-core VM.

usage::

    python examples/benchmarks/bench_mle.py                      # frame 000001 of the four scenes
    python examples/benchmarks/bench_mle.py --rounds 3 --json mle.json
    python examples/benchmarks/bench_mle.py --scenes 0000 --objects 025_mug
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_basins import pairs as ycbv_pairs  # noqa: E402  (the pairs of ycbv_eval)

#: Stages printed per pair, in this order (the others are summed under "other").
STAGES = ("coarse_search", "eq2_solve", "refine", "hop", "modes", "polish", "eq2_certify_wait")


def build(root: Path, frame: str, obj: str) -> dict[str, Any]:
    """The inputs of ``estimate_mle`` as ``certpose pose --ycbv`` builds them (see ``run_ycbv``
    and ``estimate_pose``)."""
    from dataclasses import replace

    from certpose.estimation.pipeline import PoseParams, _scene_for, likelihood_params_for
    from certpose.geometry.features import FPFHBackbone
    from certpose.io.cache import default_cache_dir, object_from_points_cached
    from certpose.io.points import read_mesh
    from certpose.io.ycbv import load_model_points, load_ycbv_frame
    from certpose.model.classifier import classify_from_mask

    params = PoseParams()
    backbone = FPFHBackbone()
    yf = load_ycbv_frame(root, frame)
    mask = yf.object_mask(obj)
    model_path = root / "models" / obj / "points.xyz"
    points = load_model_points(model_path)
    scene = _scene_for(yf.frame, mask, params, backbone)
    model = object_from_points_cached(points, backbone, voxel_size=params.voxel_size, name=obj,
                                      cache_dir=default_cache_dir(),
                                      revolution="auto" if params.model_revolution else None,
                                      mesh=read_mesh(model_path, name="model"))
    params = replace(params, likelihood=likelihood_params_for(params.likelihood, backbone))
    frame_m = yf.frame.with_mask(mask)
    cls = classify_from_mask(scene, frame_m, params=params.classifier)
    return {"scene": scene, "cls": cls, "model": model, "params": params,
            "viewpoint": frame_m.T_world_camera[:3, 3], "T_world_camera": frame_m.T_world_camera}


def run(inputs: dict[str, Any], seed: int) -> tuple[float, float, Any]:
    """Wall and CPU seconds (all threads of the process) of one ``estimate_mle`` and its result
    (the CLI's seed)."""
    from certpose.estimation.mle import estimate_mle

    p = inputs["params"]
    t, c = time.perf_counter(), time.process_time()
    mle = estimate_mle(inputs["scene"], inputs["cls"], inputs["model"], params=p.mle,
                       likelihood_params=p.likelihood, viewpoint=inputs["viewpoint"], rng=seed)
    return time.perf_counter() - t, time.process_time() - c, mle


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ycbv", type=Path, default=ROOT.parent / "shared" / "data" / "ycbv")
    ap.add_argument("--scenes", default="0000,0002,0049,0050")
    ap.add_argument("--frame", default="000001", help="the frame of every scene (default 000001)")
    ap.add_argument("--min-px", type=int, default=2000, help="least mask pixels of an object")
    ap.add_argument("--objects", nargs="+", default=None, help="only these objects")
    ap.add_argument("--rounds", type=int, default=2,
                    help="passes over all pairs; the first only warms unless 1 (default 2)")
    ap.add_argument("--seed", type=int, default=0, help="estimate_mle's seed (the CLI's default 0)")
    ap.add_argument("--json", type=Path, default=None,
                    help="write per pair and round: seconds, stages, pose, eq. (1), modes")
    args = ap.parse_args()
    if not args.ycbv.is_dir():
        raise SystemExit(f"YCB-Video data not found at {args.ycbv}")
    if args.rounds < 1:
        raise SystemExit(f"--rounds must be >= 1, got {args.rounds}")
    pairs = list(ycbv_pairs(args.ycbv, args.scenes.split(","), [args.frame], args.objects, args.min_px))
    if not pairs:
        raise SystemExit("no pair to pose")
    t = time.perf_counter()
    inputs = [build(args.ycbv, f, o) for f, o in pairs]
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}; {len(pairs)} pairs built "
          f"in {time.perf_counter() - t:.1f} s (not timed below); {args.rounds} round(s)", flush=True)
    timed = range(1 if args.rounds > 1 else 0, args.rounds)
    seconds: dict[int, list[float]] = {i: [] for i in range(len(pairs))}
    cpu: dict[int, list[float]] = {i: [] for i in range(len(pairs))}
    stages: dict[int, list[dict[str, float]]] = {i: [] for i in range(len(pairs))}
    records = []
    for r in range(args.rounds):
        for i, ((frame, obj), inp) in enumerate(zip(pairs, inputs, strict=True)):
            wall, cpu_s, mle = run(inp, args.seed)
            if r in timed:
                seconds[i].append(wall)
                cpu[i].append(cpu_s)
                stages[i].append(dict(mle.timings))
            records.append({"round": r, "frame": frame, "object": obj, "seconds": wall,
                            "cpu_seconds": cpu_s,
                            "timings": mle.timings, "T_scene_object": mle.T_scene_object.tolist(),
                            "log_likelihood": mle.log_likelihood, "hypothesis": mle.hypothesis,
                            "evaluations": mle.num_evaluations,
                            "modes": [m.to_dict() for m in mle.modes]})
            tag = "warm-up" if r not in timed else f"round {r}"
            print(f"{tag:<8} {frame} {obj:<22} {wall:5.2f} s ({cpu_s:5.2f} CPU s)  {len(mle.modes):2d} modes  "
                  f"eq.(1) {mle.log_likelihood:10.2f}", flush=True)
    print(f"\n{'pair':<34} {'median':>6} " + " ".join(f"{s[:8]:>8}" for s in STAGES)
          + "    other      CPU")
    medians, cpus = [], []
    for i, (frame, obj) in enumerate(pairs):
        med = statistics.median(seconds[i])
        medians.append(med)
        st = {k: statistics.median(d.get(k, 0.0) for d in stages[i]) for k in STAGES}
        other = med - sum(st.values())
        cpus.append(statistics.median(cpu[i]))
        print(f"{frame + ' ' + obj:<34} {med:6.2f} " + " ".join(f"{st[k]:8.2f}" for k in STAGES)
              + f" {other:8.2f} {cpus[-1]:8.2f}")
    print(f"\nestimate_mle per pair: median {statistics.median(medians):.2f} s, max {max(medians):.2f} s "
          f"({pairs[int(np.argmax(medians))][1]}), sum {sum(medians):.1f} s over {len(pairs)} pairs; "
          f"CPU median {statistics.median(cpus):.2f} s, sum {sum(cpus):.1f} s; "
          f"load average {os.getloadavg()[0]:.2f}")
    if args.json is not None:
        args.json.write_text(json.dumps(records, indent=1))


if __name__ == "__main__":
    main()
