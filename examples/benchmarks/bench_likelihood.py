"""Throughput of eq. (1) (batched, numba) for a 2,000-point object.

Usage::

    python examples/benchmarks/bench_likelihood.py [--ycbv ../shared/data/ycbv] [--points 2000]

The scene is YCB-Video frame 0000/000001 (whole frame, 5 mm voxels, FPFH descriptors, d = 33)
and the object the mug's model points; without the data folder, the synthetic mug scene. Poses
are drawn around the true pose (every object point near observed surfaces: the expensive case)
and uniformly in the scene's box. Prints poses per second for several batch sizes, and the CPU
time per point evaluation.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def _scene(ycbv: Path | None, voxel: float):
    from certpose.geometry.features import FPFHBackbone
    from certpose.model.classifier import classify_from_mask
    from certpose.model.scene import build_scene_field

    bb = FPFHBackbone()
    if ycbv is not None and (ycbv / "0000" / "000001-meta.mat").is_file():
        from certpose.io.ycbv import load_model_points, load_ycbv_frame

        yf = load_ycbv_frame(ycbv, "0000/000001")
        scene = build_scene_field(yf.frame, bb, voxel_size=voxel)
        cls = classify_from_mask(scene, yf.frame, yf.object_mask("025_mug"))
        pts = load_model_points(ycbv / "models" / "025_mug" / "points.xyz")
        return "YCB-Video 0000/000001 (whole frame)", scene, cls, pts, yf.poses["025_mug"], bb
    from certpose.data.synthetic import make_mug_scene

    sc = make_mug_scene(rng=0, n_model_points=6000)
    scene = build_scene_field(sc.frame, bb, voxel_size=voxel)
    cls = classify_from_mask(scene, sc.frame, sc.object_mask)
    return "synthetic mug scene", scene, cls, sc.model_points, sc.T_camera_object, bb


def main() -> None:
    from certpose.geometry.objects import object_from_points
    from certpose.model.likelihood import PoseLikelihood
    from solvers.lie import make_transform

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ycbv", type=Path, default=Path(__file__).resolve().parents[3] / "shared" / "data" / "ycbv")
    ap.add_argument("--points", type=int, default=2000)
    ap.add_argument("--voxel-size", type=float, default=0.005)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    name, scene, cls, model_pts, T_gt, bb = _scene(args.ycbv, args.voxel_size)
    obj = object_from_points(model_pts, bb, voxel_size=0.002).subsample(args.points, rng=0)
    lik = PoseLikelihood(scene, cls, obj)
    rng = np.random.default_rng(0)
    near = np.stack([T_gt @ make_transform(Rotation.from_rotvec(rng.normal(scale=0.2, size=3)).as_matrix(),
                                           rng.normal(scale=0.01, size=3)) for _ in range(10_000)])
    lo, hi = scene.bounds
    anywhere = np.stack([make_transform(Rotation.random(random_state=rng).as_matrix(), rng.uniform(lo, hi)) for _ in range(10_000)])
    print(f"scene: {name}, grid {scene.shape}, {scene.counts()['occupied']} occupied voxels, "
          f"d = {scene.dim}; object: {len(obj)} points")
    lik(near[:32])
    lik(near[:1])  # compile / load both kernels
    for label, poses in (("near the true pose", near), ("uniform in the scene box", anywhere)):
        for batch in (1, 64, 1024, 10_000):
            best, cpu_best = 0.0, 0.0
            n = min(len(poses), max(batch, 2000))
            for _ in range(args.repeats):
                t, c = time.perf_counter(), time.process_time()
                for s in range(0, n, batch):
                    lik(poses[s:s + batch])
                wall, cpu = time.perf_counter() - t, time.process_time() - c
                best = max(best, n / wall)
                cpu_best = max(cpu_best, n / max(cpu, 1e-9))
            ns_per_point = 1e9 / (cpu_best * len(obj))
            print(f"{label:26s} batch {batch:6d}: {best:9.0f} poses/s "
                  f"({cpu_best:8.0f} per CPU-second, {ns_per_point:5.1f} ns per point)")


if __name__ == "__main__":
    main()
