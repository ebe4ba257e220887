"""``certpose bop``: datasets in the BOP layout (conversion of the shared YCB-Video frames and the
demo scene), and the ``--bop`` runs of ``certpose pose`` and ``certpose object build``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

_DESCRIPTION = """\
Write data as a BOP-layout dataset folder (models/ with models_info.json and millimetre PLY
models, test/<scene>/ with rgb/, depth/, mask_visib/, scene_camera.json, scene_gt.json,
scene_gt_info.json, and test_targets_bop19.json), for `certpose pose --bop` and
`certpose score --bop`.

examples:
  certpose bop convert-ycbv ../shared/data/ycbv /tmp/ycbv_bop
  certpose bop convert-demo /tmp/demo_bop
"""


def add_parser(subparsers: Any) -> None:
    from certpose.cli import add_common

    p = subparsers.add_parser("bop", help="write YCB-Video frames or the demo as a BOP dataset",
                              description=_DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="bop_command", metavar="ACTION", required=True)
    c = sub.add_parser("convert-ycbv", help="YCB-Video frames as a BOP folder",
                       description="Write YCB-Video frames (ROOT/<scene>/<frame>-*, "
                                   "ROOT/models/) as a BOP folder OUT.")
    c.add_argument("root", metavar="ROOT", help="YCB-Video folder")
    c.add_argument("out", metavar="OUT", help="the BOP folder to write")
    c.add_argument("--frames", nargs="+", metavar="SCENE/FRAME", default=None,
                   help="the frames to convert (default: all under ROOT)")
    c.add_argument("--min-visib-fract", type=float, default=0.1, metavar="F",
                   help="instances at least this visible are targets (default: 0.1, BOP 2019)")
    add_common(c)
    c.set_defaults(func=run_convert)
    d = sub.add_parser("convert-demo", help="the synthetic demo scene as a BOP folder",
                       description="Write the synthetic mug scene of `certpose pose --demo` as "
                                   "a BOP folder OUT (one image, the mug as object 1).")
    d.add_argument("out", metavar="OUT", help="the BOP folder to write")
    add_common(d, seed_help="the demo scene's seed (default: 0)")
    d.set_defaults(func=run_convert)


def _check_out(out: Path) -> None:
    from certpose.cli import CLIError

    if out.exists() and not out.is_dir():
        raise CLIError(f"{out} exists and is not a folder")
    if not out.parent.is_dir():
        raise CLIError(f"the folder {out.parent} of {out} does not exist")


def run_convert(args: argparse.Namespace) -> int:
    from certpose.cli import CLIError, busy, check_json_output, emit_json, say

    check_json_output(args)
    out = Path(args.out)
    _check_out(out)
    with busy(args, f"certpose bop {args.bop_command}"):
        if args.bop_command == "convert-ycbv":
            from certpose.bop.convert import convert_ycbv

            if not Path(args.root).is_dir():
                raise CLIError(f"{args.root} is not a directory")
            if not 0.0 <= args.min_visib_fract <= 1.0:
                raise CLIError(f"--min-visib-fract must be in [0, 1], got {args.min_visib_fract}")
            summary = convert_ycbv(args.root, out, frames=args.frames,
                                   min_visib_fract=args.min_visib_fract)
        else:
            from certpose.bop.convert import convert_demo

            summary = convert_demo(out, rng=args.seed)
    say(args, f"wrote {out}: {summary['images']} image(s), {summary['instances']} instance(s), "
              f"{summary['targets']} target(s), objects {summary['objects']}")
    emit_json(args, summary)
    sys.stdout.flush()
    return 0
