"""Benchmark: building the scene field ``f_scn`` from one real 640x480 YCB-Video frame.

Usage::

    python examples/benchmarks/bench_scene.py [--ycbv ../shared/data/ycbv] [--frame 0000/000001] [--repeat 5]

Reports the wall time of :func:`certpose.model.scene.build_scene_field` (FPFH descriptors, free-space
carving) for a few regions of interest: the first call and the median of the following calls
(open3d's one-off import, ~1.5-2 s, is timed separately). Target: <= 3 s per frame.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

DEFAULT_ROOT = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "ycbv"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ycbv", type=Path, default=DEFAULT_ROOT)
    parser.add_argument("--frame", default="0000/000001")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    t0 = time.perf_counter()
    from certpose.io.ycbv import load_ycbv_frame
    from certpose.model.scene import build_scene_field

    data = load_ycbv_frame(args.ycbv, args.frame)
    print(f"load frame {args.frame}: {time.perf_counter() - t0:.2f} s (imports included)")
    t0 = time.perf_counter()
    import open3d  # noqa: F401  (imported lazily by the first build otherwise)

    print(f"import open3d: {time.perf_counter() - t0:.2f} s (once per process, not counted below)")

    all_objects = np.zeros(data.frame.shape, dtype=bool)
    for name in data.class_names:
        all_objects |= data.object_mask(name)
    cases = [
        ("mug ROI, 5 mm", dict(voxel_size=0.005, roi_mask=data.object_mask("025_mug"), margin=0.05)),
        ("all objects ROI, 5 mm", dict(voxel_size=0.005, roi_mask=all_objects, margin=0.05)),
        ("whole frame, 1 cm", dict(voxel_size=0.01)),
        ("whole frame, 5 mm, depth <= 1 m", None),
    ]
    for label, kwargs in cases:
        if kwargs is None:
            near = (data.frame.depth > 0) & (data.frame.depth <= 1.0)
            kwargs = dict(voxel_size=0.005, roi_mask=near, margin=0.0)
        times = []
        for _ in range(args.repeat + 1):
            t = time.perf_counter()
            scene = build_scene_field(data.frame, **kwargs)
            times.append(time.perf_counter() - t)
        c = scene.counts()
        print(
            f"{label:32s} grid {scene.shape} ({scene.n_voxels} voxels, {c['occupied']} occupied, "
            f"{c['empty']} empty): first {times[0]:.2f} s, median {statistics.median(times[1:]):.2f} s"
        )


if __name__ == "__main__":
    main()
