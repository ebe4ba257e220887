"""How the mug's hidden-handle arc, and so the arc targets, depend on the per-pixel judge.

``bench_mug_arc.py`` scores the pose distribution against the arc of turns that
:func:`certpose.model.arc.free_space_arc` calls hidden with its per-pixel defaults (a turn is
free when at most 20 more of the model's points than at the truth stand more than 1 cm in
front of the observed depth). This script recomputes that arc under stricter judges and scores
the same distribution (``certpose pose``'s default, 2,000 particles) against each:

* ``tol``/``mv``: the depth tolerance (mm) and the points allowed beyond the baseline;
* ``handle``: only the handle's points are tested (the body's points do not move when the mug
  turns about its axis), with the truth's own violations as baseline.

On the demo it also gives the exact arc (the rendered scene:
:meth:`certpose.data.synthetic.SyntheticScene.hidden_handle_arc`), against which the judges'
arcs can be checked: the default judge's arc is wider than the exact one, so the bins at its
ends hold poses whose handle the exact render shows.

usage::

    python examples/benchmarks/bench_arc_judge.py [--ycbv ../shared/data/ycbv] [--seeds 0 1 2 3 4]
        [--frames 000001 ...] [--samples 2000]
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

JUDGES = [("default", 0.01, 20, False), ("mv 5", 0.01, 5, False), ("mv 0", 0.01, 0, False),
          ("5 mm, mv 5", 0.005, 5, False), ("handle, mv 0", 0.01, 0, True),
          ("handle, mv 3", 0.01, 3, True)]


def handle_points(points: np.ndarray, centre: np.ndarray, margin: float = 0.006) -> np.ndarray:
    """The model points farther than the body's median radius plus ``margin`` (metres) from the
    body axis (object z through ``centre``): the handle."""
    r = np.linalg.norm(points[:, :2] - centre[:2], axis=1)
    return points[r > np.median(r) + margin]


def judged(scene, points, G, centre, dist) -> list[str]:  # noqa: ANN001
    from bench_mug_arc import AXIS, figures

    from certpose.model.arc import free_space_arc

    out = []
    for name, tol, mv, handle in JUDGES:
        pts = handle_points(points, centre) if handle else points
        arc = free_space_arc(scene, pts, G, centre=centre, tolerance=tol, max_violations=mv,
                             baseline="reference")
        if arc.arc is None:
            out.append(f"{name:>13}: no arc about the truth")
            continue
        f = figures(dist, G, arc, centre, AXIS)
        out.append(f"{name:>13}: arc ({f['arc'][0]:6.1f}, {f['arc'][1]:5.1f}) in arc {f['in_arc']:.2f}, "
                   f"> 20 out {f['far_out']:.2f}, bins {f['bins']:.2f}")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ycbv", type=Path, default=Path(__file__).resolve().parents[3] / "shared" / "data" / "ycbv")
    ap.add_argument("--samples", type=int, default=2000)
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2, 3, 4])
    ap.add_argument("--frames", nargs="*", default=["000001", "000002", "000003", "000004", "000005"])
    args = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_arc import body_axis_offset
    from bench_mug_arc import AXIS, figures

    from certpose.data.synthetic import make_mug_scene
    from certpose.estimation.pipeline import PoseParams, run_demo, run_ycbv
    from certpose.io.cache import default_cache_dir
    from certpose.io.ycbv import load_model_points
    from certpose.sampling.sampler import ISParams

    params = replace(PoseParams(), sampler=ISParams(draws=max(10_000, args.samples), resample=args.samples))
    print(f"load {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    for seed in args.seeds:
        res = run_demo(params=params, rng=seed, cache_dir=default_cache_dir())
        sc = make_mug_scene(rng=np.random.default_rng(seed))
        G = res.T_world_camera @ res.T_camera_object_gt
        fx = figures(res.distribution, G, sc.hidden_handle_arc(step=0.5), np.zeros(3), AXIS)
        print(f"demo {seed}: exact arc ({fx['arc'][0]:6.1f}, {fx['arc'][1]:5.1f}) in arc {fx['in_arc']:.2f}, "
              f"> 20 out {fx['far_out']:.2f}, bins {fx['bins']:.2f}")
        print("\n".join(judged(res.scene, sc.model_points, G, np.zeros(3), res.distribution)), flush=True)
    if args.frames and args.ycbv.is_dir():
        path = args.ycbv / "models" / "025_mug" / "points.xyz"
        pts = load_model_points(path)
        centre = body_axis_offset(pts)
        for frame in args.frames:
            res = run_ycbv(args.ycbv, f"0000/{frame}", "025_mug", path, params=params, rng=0,
                           cache_dir=default_cache_dir())
            G = res.T_world_camera @ res.T_camera_object_gt
            print(f"0000/{frame}:")
            print("\n".join(judged(res.scene, pts, G, centre, res.distribution)), flush=True)
    print(f"load {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
