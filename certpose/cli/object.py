"""``certpose object build``: an object model with appearance from posed RGB-D views (YCB-Video's,
or a JSON manifest of any camera's)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

_DESCRIPTION = """\
Build an object model the paper's way: colour and describe the model points from RGB-D views in
which the object's pose is known (YCB-Video's ground-truth poses and labels). The descriptors join
FPFH (shape) to local colour statistics (print and texture), so that a box's printed front differs
from its back; points that no view saw carry "no information". The model is saved as .npz and used
with `certpose pose --object-model`. Never evaluate a model on the scene whose views built it.

examples:
  certpose object build --ycbv ../shared/data/ycbv --object 006_mustard_bottle \\
      --views 0002/000001 0002/000010 0002/000020 -o mustard_0002.npz
  certpose object build --posed-views my_views.json --model mug.ply --object mug -o mug.npz
"""


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "object",
        help="build object models with appearance from posed RGB-D views",
        description="Object models for `certpose pose --object-model`.",
    )
    sub = p.add_subparsers(dest="object_command", metavar="ACTION", required=True)
    b = sub.add_parser(
        "build",
        help="colour and describe model points from posed RGB-D views",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    src = b.add_mutually_exclusive_group(required=True)
    src.add_argument("--ycbv", metavar="DIR",
                     help="YCB-Video folder (with <scene>/ and models/), with --views")
    src.add_argument("--posed-views", metavar="VIEWS.json",
                     help="your own posed views: a JSON manifest of colour, depth and mask images "
                          "with each view's T_camera_object and the camera's intrinsics "
                          "(certpose.io.views; needs --model)")
    src.add_argument("--bop", metavar="DIR", default=None,
                     help="a BOP dataset: every object's geometry-only model of DIR/models built "
                          "into the model cache read by `certpose pose --bop` (--objects, "
                          "--split, --revolution; no -o)")
    b.add_argument("--objects", type=int, nargs="+", metavar="ID", default=None,
                   help="with --bop: these object ids only")
    b.add_argument("--split", default="test", help=argparse.SUPPRESS)
    b.add_argument("--revolution", action="store_true",
                   help="with --bop: the models `certpose pose --bop --revolution` uses")
    b.add_argument("--views", metavar="SCENE/FRAME", nargs="+", default=None,
                   help="with --ycbv: frames whose ground-truth pose and label colour the model")
    b.add_argument("--object", metavar="NAME", default=None,
                   help="the object's name (YCB-Video's, with --ycbv)")
    b.add_argument("--model", metavar="POINTS", default=None,
                   help="object model points, metres (default with --ycbv: "
                        "DIR/models/NAME/points.xyz)")
    b.add_argument("--voxel-size", type=float, default=0.005, metavar="M",
                   help="voxel size in metres; use the one given to `certpose pose` (default: 0.005)")
    # Defaults: AppearanceBackbone's (one place; imported only when the command runs).
    b.add_argument("--color-weight", type=float, default=None, metavar="W",
                   help="share of colour in the descriptor similarity, in [0, 1] (default: 0.9)")
    b.add_argument("--similarity-scale", type=float, default=None, metavar="S",
                   help="eq. (1)'s beta is multiplied by S for scenes and this model (default: 4)")
    b.add_argument("--sampling", choices=("voxel", "surface"), default="surface",
                   help="model points spread evenly over a surface reconstructed from them, "
                        "weighted by area in eq. (1) (default), or averaged per voxel")
    b.add_argument("-o", "--output", metavar="OUT.npz", default=None,
                   help="where to save the model (required but with --bop)")
    from certpose.cli import add_common

    add_common(b, json_help="also write a summary of the model as JSON to OUT ('-': standard "
                            "output)")
    b.set_defaults(func=run_build)


def run_build(args: argparse.Namespace) -> int:
    import math
    from dataclasses import replace

    from certpose.cli import CLIError, busy, check_json_output, emit_json, say
    from certpose.estimation.pipeline import build_ycbv_object_model
    from certpose.geometry.appearance import AppearanceBackbone

    if args.bop is not None:
        from certpose.cli.bop import run_object_build

        return run_object_build(args)
    if args.output is None:
        raise CLIError("-o/--output OUT.npz is required")
    if args.objects is not None or args.revolution:
        raise CLIError("--objects and --revolution need --bop DIR")
    check_json_output(args)
    if args.ycbv is not None:
        root = Path(args.ycbv)
        if not root.is_dir():
            raise CLIError(f"--ycbv {root} is not a directory")
        if args.views is None or args.object is None:
            raise CLIError("--ycbv needs --views SCENE/FRAME ... and --object NAME")
    else:
        if args.views is not None:
            raise CLIError("--views needs --ycbv (--posed-views lists its own views)")
        if args.model is None:
            raise CLIError("--posed-views needs --model POINTS (the object's points, metres)")
        if not Path(args.posed_views).is_file():
            raise CLIError(f"--posed-views {args.posed_views} does not exist")
    if args.model is not None and not Path(args.model).is_file():
        raise CLIError(f"--model {args.model} does not exist")
    if not (math.isfinite(args.voxel_size) and args.voxel_size > 0):
        raise CLIError(f"--voxel-size must be positive, got {args.voxel_size}")
    backbone = AppearanceBackbone()
    if args.color_weight is not None:
        if not 0.0 <= args.color_weight <= 1.0:
            raise CLIError(f"--color-weight must be in [0, 1], got {args.color_weight}")
        backbone = replace(backbone, color_weight=args.color_weight)
    if args.similarity_scale is not None:
        if not (math.isfinite(args.similarity_scale) and args.similarity_scale > 0):
            raise CLIError(f"--similarity-scale must be positive, got {args.similarity_scale}")
        backbone = replace(backbone, similarity_scale=args.similarity_scale)
    out = Path(args.output)
    if out.suffix != ".npz":
        raise CLIError(f"-o {out} must end in .npz")
    if not out.parent.is_dir():
        raise CLIError(f"-o {out}: the folder {out.parent} does not exist")
    from certpose.io.output import atomic_path, check_output_path

    check_output_path(out, what="-o output", force=args.force)
    name = args.object or Path(args.model).stem
    with busy(args, "certpose object build"):
        if args.ycbv is not None:
            built = build_ycbv_object_model(
                root, args.views, args.object, args.model,
                backbone=backbone,
                voxel_size=args.voxel_size, sampling=args.sampling)
        else:
            from certpose.geometry.appearance import object_from_posed_views
            from certpose.io.views import load_posed_views
            from certpose.io.ycbv import load_model_points

            built = object_from_posed_views(
                load_model_points(args.model), load_posed_views(args.posed_views), backbone,
                voxel_size=args.voxel_size, name=name, sampling=args.sampling)
    with atomic_path(out) as tmp:  # a second writer or Ctrl-C never leaves a partial archive
        built.save(tmp)
    n, seen = len(built.model), int(built.observed.sum())
    say(args, f"object model {name}: {n} points, {seen} seen by {len(built.views)} "
              f"view(s) ({100.0 * built.seen_fraction:.0f}% of its surface), the other {n - seen} "
              "carry no appearance information")
    say(args, f"built from scene(s) {', '.join(built.scenes)}: do not evaluate it on them")
    say(args, f"wrote {out}")
    emit_json(args, {"object": name, "output": str(out), "points": n, "observed": seen,
                     "seen_fraction": built.seen_fraction,
                     "views": list(built.views), "scenes": list(built.scenes),
                     "voxel_size": args.voxel_size, "color_weight": backbone.color_weight,
                     "similarity_scale": backbone.similarity_scale})
    sys.stdout.flush()
    return 0
