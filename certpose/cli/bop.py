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


# ---- certpose pose --bop ----------------------------------------------------------------------

POSE_EPILOG = """\
BOP datasets (--bop DIR): every target of DIR's targets file (default
DIR/test_targets_bop19.json) is posed with its visible mask (mask_visib) as p_O, the
geometry-only model of DIR/models (built once and cached), and --seed for every instance; the
BOP results file --out (scene_id,im_id,obj_id,score,R,t,time: R row-major, t in mm, time per
image; score = eq. (1) at the pose) and its side file OUT.certpose.csv (certificate, gap,
modes, ESS, errors vs the ground truth) are written image by image as images finish. The work
runs on Dask like `certpose bench` (--workers N: a local cluster, --workers 0: this process,
--scheduler ADDRESS: a running cluster); a killed run continues with --resume. Score the file
with `certpose score --bop DIR OUT`.
  certpose pose --bop /tmp/ycbv_bop --out results.csv --workers 2
"""


def add_pose_options(p: argparse.ArgumentParser, sources: Any) -> None:
    """``certpose pose``'s --bop source and its options (a group of their own)."""
    sources.add_argument("--bop", metavar="DIR", default=None,
                         help="a BOP dataset folder: pose every target of its targets file "
                              "(with --out; see below)")
    g = p.add_argument_group("BOP datasets (--bop)")
    g.add_argument("--split", default="test", help="the split folder (default: test)")
    g.add_argument("--targets", metavar="FILE", default=None,
                   help="targets file (default: DIR/test_targets_bop19.json)")
    g.add_argument("--out", metavar="RESULTS.csv", default=None,
                   help="the BOP results file to write (side file RESULTS.certpose.csv)")
    g.add_argument("--workers", type=int, default=None, metavar="N",
                   help="Dask workers of a local cluster (default: one per core; 0: in this "
                        "process)")
    g.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="a running Dask scheduler (e.g. tcp://host:8786)")
    g.add_argument("--resume", action="store_true",
                   help="continue a run: keep the images already complete in --out")
    g.add_argument("--particles-dir", metavar="DIR", default=None,
                   help="with --samples N: each instance's particles as DIR/<scene>_<im>_<obj>_"
                        "<gt>.npz")
    p.epilog = (p.epilog or "") + POSE_EPILOG


def check_pose_options(args: argparse.Namespace) -> None:
    from certpose.cli import CLIError

    if args.bop is None:
        bop_only = [f"--{o.replace('_', '-')}" for o in ("targets", "out", "workers",
                                                         "scheduler", "particles_dir")
                    if getattr(args, o) is not None]
        bop_only += [f"--{o}" for o in ("resume",) if getattr(args, o)]
        if bop_only or args.split != "test":
            raise CLIError(f"{'/'.join(bop_only) or '--split'} need(s) --bop DIR")
        return
    refused = [f"--{o.replace('_', '-')}" for o in ("frame", "object", "model", "object_model",
                                                    "box", "box_margin", "save_problem",
                                                    "particles", "plot", "axis", "intrinsics",
                                                    "depth_scale", "mask")
               if getattr(args, o, None) is not None]
    if args.classifier != "mask":
        refused.append("--classifier best-buddies")
    if refused:
        raise CLIError(f"{', '.join(refused)} cannot combine with --bop (every target is posed "
                       "with its visible mask and the dataset's model)")
    if args.out is None:
        raise CLIError("--bop needs --out RESULTS.csv")
    if not Path(args.bop).is_dir():
        raise CLIError(f"--bop {args.bop} is not a directory")
    if args.workers is not None and args.workers < 0:
        raise CLIError(f"--workers must be >= 0, got {args.workers}")
    if args.scheduler is not None and args.workers is not None:
        raise CLIError("--scheduler and --workers exclude each other")
    if args.resume and args.force:
        raise CLIError("--resume and --force exclude each other")
    if args.particles_dir is not None:
        if args.samples == 0:
            raise CLIError("--particles-dir needs --samples N")
        if not Path(args.particles_dir).is_dir():
            raise CLIError(f"--particles-dir {args.particles_dir} is not a directory")
    if args.require_certificate and args.no_certify:
        raise CLIError("--require-certificate and --no-certify exclude each other")
    if args.samples < 0:
        raise CLIError(f"--samples must be >= 0, got {args.samples}")
    out = Path(args.out)
    if not out.parent.is_dir():
        raise CLIError(f"--out {out}: the folder {out.parent} does not exist")
    if out.exists() and not (args.resume or args.force):
        raise CLIError(f"--out {out} already exists; pass --resume to continue that run or "
                       "--force to overwrite it")


def _pose_params(args: argparse.Namespace) -> Any:
    from dataclasses import replace

    from certpose.estimation.mle import MLEParams
    from certpose.estimation.pipeline import PoseParams

    params = PoseParams(voxel_size=args.voxel_size, model_revolution=args.revolution)
    if args.free_space is not None:
        params = replace(params, likelihood=replace(params.likelihood, free_space=args.free_space))
    if args.no_certify:
        params = replace(params, mle=replace(MLEParams(), certify=False))
    if args.samples:
        from certpose.sampling.sampler import ISParams

        params = replace(params, sampler=ISParams(draws=max(10_000, args.samples),
                                                  resample=args.samples),
                         sampling_method=args.method)
    return params


def run_pose(args: argparse.Namespace) -> int:
    """``certpose pose --bop DIR --out RESULTS.csv``."""
    import contextlib

    from certpose.bop.runner import BOPRunInterrupted, run_bop_poses
    from certpose.cli import (
        EXIT_INTERRUPTED,
        CLIError,
        check_json_output,
        emit_json,
        say,
        show_progress,
    )
    from certpose.io.cache import default_cache_dir

    check_pose_options(args)
    check_json_output(args)
    params = _pose_params(args)
    bar = None
    if show_progress(args) and sys.stderr.isatty():
        with contextlib.suppress(ImportError):
            from tqdm import tqdm

            bar = tqdm(desc="certpose pose --bop", unit="target", leave=False)
    try:
        summary = run_bop_poses(
            args.bop, args.out, split=args.split, targets=args.targets, params=params,
            seed=args.seed, workers=args.workers, scheduler=args.scheduler, resume=args.resume,
            force=args.force, cache_dir=default_cache_dir(), particles_dir=args.particles_dir,
            progress=None if bar is None else bar.update)
    except BOPRunInterrupted as exc:
        print(f"certpose pose: {exc}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except FileExistsError as exc:
        raise CLIError(str(exc)) from None
    finally:
        if bar is not None:
            bar.close()
    say(args, f"{summary.message} in {summary.wall_seconds:.1f} s "
              f"(workers: {summary.workers})")
    say(args, f"wrote {summary.results} and {summary.side}")
    emit_json(args, {"input": {"bop": args.bop, "split": args.split, "targets": args.targets,
                               "seed": args.seed, "voxel_size": args.voxel_size,
                               "samples": args.samples},
                     **summary.to_dict()})
    sys.stdout.flush()
    if not summary.success:
        return 1
    if args.require_certificate:
        import csv

        from certpose.bop.results import side_path

        with side_path(args.out).open(newline="", encoding="utf-8") as fh:
            uncertified = sum(r["certified"] != "True" for r in csv.DictReader(fh))
        if uncertified:
            print(f"certpose pose: --require-certificate: {uncertified} instance(s) not "
                  "certified", file=sys.stderr)
            return 1
    return 0


# ---- certpose object build --bop ---------------------------------------------------------------

def run_object_build(args: argparse.Namespace) -> int:
    """``certpose object build --bop DIR [--objects ID ...]``: every object's geometry-only
    model built once and kept in the model cache, where `certpose pose --bop` reads it."""
    from certpose.bop.pose import object_model
    from certpose.cli import CLIError, busy, check_json_output, emit_json, say
    from certpose.estimation.pipeline import PoseParams
    from certpose.io.bop import BOPDataset
    from certpose.io.cache import default_cache_dir

    check_json_output(args)
    if args.output is not None or args.views is not None or args.model is not None:
        raise CLIError("--bop builds every object of DIR/models into the model cache: no "
                       "-o/--views/--model")
    cache = default_cache_dir()
    if cache is None:
        raise CLIError("the model cache is off (CERTPOSE_CACHE_DIR is empty): --bop has nowhere "
                       "to keep the models")
    ds = BOPDataset(args.bop, args.split)
    ids = ds.obj_ids if args.objects is None else args.objects
    unknown = sorted(set(ids) - set(ds.obj_ids))
    if unknown:
        raise CLIError(f"--objects {unknown} are not in {args.bop}/models/models_info.json")
    params = PoseParams(voxel_size=args.voxel_size, model_revolution=args.revolution)
    built = []
    with busy(args, "certpose object build --bop"):
        for obj_id in ids:
            model = object_model(ds, obj_id, params, cache_dir=cache)
            built.append({"obj_id": obj_id, "points": len(model.points)})
            say(args, f"object {obj_id}: {len(model.points)} model points")
    say(args, f"{len(built)} object model(s) in {cache}")
    emit_json(args, {"bop": args.bop, "cache": str(cache), "objects": built,
                     "voxel_size": args.voxel_size})
    return 0
