"""The maximum-likelihood pose of an object in an RGB-D frame, with its certificate and errors.

Usage::

    python examples/pose_from_rgbd.py                          # synthetic mug scene (no data)
    python examples/pose_from_rgbd.py --ycbv ../shared/data/ycbv --frame 0000/000001 --object 025_mug
    python examples/pose_from_rgbd.py --ycbv ../shared/data/ycbv --frame 0049/000001 \
        --object 010_potted_meat_can --box-only --views 0002/000001 0002/000010
    python examples/pose_from_rgbd.py --files color.png depth.png --intrinsics 615 615 320 240 \
        --depth-scale 1000 --mask mask.png --model mug.ply     # any camera's frame

The YCB-Video path uses the frame's ground-truth mask as the classifier and the object's
``points.xyz`` as the model; it reports the errors against the frame's ground truth. With
``--box-only`` no mask is used: the object's 2-D box (``box.txt``, what a detector gives) is the
region of interest and ``p_O`` comes from best buddies; ``--views`` builds the object model with
appearance from posed views of another scene (never of the scene evaluated). ``--files`` poses an
object in a frame of any camera: colour and depth images, pinhole intrinsics, the depth units per
metre, the object's mask and its model points (``run_rgbd``; no ground truth, so no errors).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from certpose.estimation.pipeline import build_ycbv_object_model, run_demo, run_rgbd, run_ycbv


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ycbv", help="YCB-Video folder (holding <scene>/ and models/)")
    parser.add_argument("--frame", default="0000/000001", help="<scene>/<frame>")
    parser.add_argument("--object", default="025_mug", help="object name, e.g. 025_mug")
    parser.add_argument("--box-only", action="store_true",
                        help="no mask: best buddies inside the object's box from box.txt")
    parser.add_argument("--views", nargs="+", default=None, metavar="SCENE/FRAME",
                        help="build an appearance model from these posed views (another scene)")
    parser.add_argument("--files", nargs=2, metavar=("COLOR", "DEPTH"), default=None,
                        help="a frame of any camera (with --intrinsics, --mask, --model)")
    parser.add_argument("--intrinsics", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"))
    parser.add_argument("--depth-scale", type=float, default=1000.0, help="depth units per metre")
    parser.add_argument("--mask", help="the object's mask image (non-zero: object)")
    parser.add_argument("--model", help="the object's model points, metres")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    if args.files:
        if args.intrinsics is None or args.mask is None or args.model is None:
            parser.error("--files needs --intrinsics, --mask and --model")
        res = run_rgbd(*args.files, args.intrinsics, depth_scale=args.depth_scale,
                       mask_path=args.mask, model_path=args.model, rng=args.seed)
    elif args.ycbv:
        model = None
        if args.views:
            if any(v.split("/")[0] == args.frame.split("/")[0] for v in args.views):
                parser.error("--views must come from another scene than --frame")
            model = build_ycbv_object_model(args.ycbv, args.views, args.object)
        res = run_ycbv(args.ycbv, args.frame, args.object, rng=args.seed, object_model=model,
                       classifier="best_buddies" if args.box_only else "mask")
    else:
        res = run_demo(rng=args.seed)
    print(f"status: {res.status} ({res.message})")
    print("T_camera_object =")
    print(np.array2string(res.T_camera_object, precision=4, suppress_small=True))
    print(f"eq. (1) log-likelihood: {res.log_likelihood:.2f}")
    # The certificate bounds eq. (2) at its minimiser, not this pose: print what it covers.
    print(f"certificate: {res.certificate_scope}")
    for k, m in enumerate(res.modes[1:], start=1):
        print(f"competing mode {k}: eq. (1) {m['log_likelihood']:.2f}, "
              f"{m['rotation_from_best_deg']:.0f} deg from the returned pose")
    if res.errors is not None:
        print(f"errors against ground truth: {res.errors}")
    return 0 if res.success else 1


if __name__ == "__main__":
    sys.exit(main())
