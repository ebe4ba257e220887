"""An object model with appearance from posed RGB-D views, then the object's pose in a scene.

Usage::

    python examples/object_model_from_views.py                      # synthetic views, then pose
    python examples/object_model_from_views.py --manifest views.json --model object.ply -o object.npz

Without arguments the example renders four views of the synthetic mug whose poses are known,
writes them as image files with a JSON manifest (the format ``certpose object build
--posed-views`` reads, :mod:`certpose.io.views`), builds the model from the manifest
(:func:`~certpose.geometry.appearance.object_from_posed_views`: model points coloured by the
views that see them, described by FPFH + colour statistics) and poses it in the demo scene.
With ``--manifest`` and ``--model`` it builds your own object's model and saves it; pose with
``certpose pose ... --object-model object.npz``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np


def write_manifest(folder: Path) -> tuple[Path, np.ndarray]:
    """Render the mug's posed views into ``folder``; return the manifest and the model points."""
    import imageio.v3 as iio

    from certpose.data.synthetic import make_mug_scene

    sc = make_mug_scene(rng=0)
    k = sc.intrinsics
    views = []
    for i, frame in enumerate(sc.render_object_views(4)):
        stem = f"mug/{i:04d}"
        iio.imwrite(folder / f"{i:04d}-color.png", frame.color)
        iio.imwrite(folder / f"{i:04d}-depth.png", np.round(frame.depth * 1000).astype(np.uint16))
        iio.imwrite(folder / f"{i:04d}-mask.png", frame.mask.astype(np.uint8) * 255)
        # The renders' world frame is the object's: T_camera_object = inv(T_world_camera).
        views.append({"name": stem, "color": f"{i:04d}-color.png", "depth": f"{i:04d}-depth.png",
                      "mask": f"{i:04d}-mask.png",
                      "T_camera_object": np.linalg.inv(frame.T_world_camera).tolist()})
    manifest = folder / "views.json"
    manifest.write_text(json.dumps({"intrinsics": [k.fx, k.fy, k.cx, k.cy], "depth_scale": 1000,
                                    "views": views}, indent=1))
    return manifest, sc.model_points


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--manifest", type=Path, help="JSON manifest of posed views (certpose.io.views)")
    ap.add_argument("--model", type=Path, help="the object's model points, metres (.ply, .xyz, ...)")
    ap.add_argument("-o", "--output", type=Path, help="where to save the model (.npz)")
    args = ap.parse_args()
    if (args.manifest is None) != (args.model is None):
        ap.error("--manifest and --model go together")

    from certpose.geometry.appearance import object_from_posed_views
    from certpose.io.views import load_posed_views

    with tempfile.TemporaryDirectory() as tmp:
        if args.manifest is None:
            manifest, points = write_manifest(Path(tmp))
        else:
            from certpose.io.ycbv import load_model_points

            manifest, points = args.manifest, load_model_points(args.model)
        built = object_from_posed_views(points, load_posed_views(manifest), name="object")
    seen = int(built.observed.sum())
    print(f"object model: {len(built.model)} points, {seen} seen by {len(built.views)} views; "
          f"built from scene(s) {', '.join(built.scenes)}")
    if args.output is not None:
        built.save(args.output)
        print(f"wrote {args.output}")
    if args.manifest is not None:
        return 0

    # Pose it in the demo scene: the scene described by the model's backbone (FPFH + colour).
    from certpose.data.synthetic import make_mug_scene
    from certpose.estimation.pipeline import estimate_pose
    from certpose.model.scene import build_scene_field

    sc = make_mug_scene(rng=1)
    scene = build_scene_field(sc.frame, built.backbone, voxel_size=0.005, roi_mask=sc.object_mask,
                              margin=0.1)
    res = estimate_pose(scene, built.model, classifier="mask", frame=sc.frame.with_mask(sc.object_mask),
                        rng=0, T_camera_object_gt=sc.T_camera_object,
                        gt_model_points=sc.model_points, symmetry_axis=(0.0, 0.0, 1.0))
    e = res.errors
    print(f"pose: {res.status}; against the truth: symmetry axis {e.symmetry_axis_deg:.1f} deg, "
          f"ADD-S {100 * e.add_s:.2f} cm (the handle is hidden: the turn about the axis is free)")
    return 0 if res.success else 1


if __name__ == "__main__":
    sys.exit(main())
