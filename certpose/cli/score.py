"""``certpose score``: the BOP 2019 scores of a results file (VSD, MSSD, MSPD, AR) with ADD(-S)
and rotation errors."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

_DESCRIPTION = """\
Score a BOP results file (scene_id,im_id,obj_id,score,R,t,time) on a BOP dataset the BOP 2019
way: VSD (the models rendered at the estimate and the ground truth by ray casting, delta 15 mm,
tau 0.05-0.5 of the diameter), MSSD (0.05-0.5 of the diameter) and MSPD (5-50 px at 640 px
width) with the models' symmetries from models_info.json, average recall per metric and
overall; beside them ADD(-S) (ADD-S for objects with symmetries) and the rotation error.

examples:
  certpose score --bop /tmp/ycbv_bop results.csv
  certpose score --bop /tmp/ycbv_bop results.csv --errors errors.csv --json scores.json
"""


def add_parser(subparsers: Any) -> None:
    from certpose.cli import add_common

    p = subparsers.add_parser("score", help="BOP 2019 scores (VSD, MSSD, MSPD, AR) of results",
                              description=_DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bop", metavar="DIR", required=True, help="the BOP dataset folder")
    p.add_argument("results", metavar="RESULTS.csv", help="the BOP results file")
    p.add_argument("--split", default="test", help="the split folder (default: test)")
    p.add_argument("--targets", metavar="FILE", default=None,
                   help="targets file (default: DIR/test_targets_bop19.json)")
    p.add_argument("--errors", metavar="OUT.csv", default=None,
                   help="also write every target instance's errors")
    add_common(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from certpose.bop.score import score_bop, write_errors
    from certpose.cli import CLIError, busy, check_json_output, emit_json, say

    check_json_output(args)
    if not Path(args.bop).is_dir():
        raise CLIError(f"--bop {args.bop} is not a directory")
    if not Path(args.results).is_file():
        raise CLIError(f"{args.results} does not exist")
    if args.errors is not None:
        from certpose.io.output import check_output_path

        check_output_path(args.errors, what="--errors output")
    with busy(args, "certpose score"):
        scores = score_bop(args.bop, args.results, split=args.split, targets=args.targets)
    ar = scores.ar
    say(args, f"{scores.estimates} estimate(s), {scores.targets} target instance(s)")
    say(args, f"AR {ar['ar']:.4f}: AR_VSD {ar['vsd']:.4f}, AR_MSSD {ar['mssd']:.4f}, "
              f"AR_MSPD {ar['mspd']:.4f}")
    say(args, f"ADD(-S) < 0.1 d: {scores.add_s['recall_0.1d']:.4f} (mean "
              f"{1000 * scores.add_s['mean_m']:.2f} mm); rotation error median "
              f"{scores.rotation_error_deg['median']:.2f} deg, mean "
              f"{scores.rotation_error_deg['mean']:.2f} deg")
    if args.errors is not None:
        say(args, f"wrote {write_errors(args.errors, scores)}")
    emit_json(args, {"input": {"bop": args.bop, "results": args.results, "split": args.split,
                               "targets": args.targets}, **scores.to_dict()})
    sys.stdout.flush()
    return 0
