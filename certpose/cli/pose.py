"""``certpose pose``: the MLE pose of an object in an RGB-D frame (YCB-Video, image files of any
camera, or the demo)."""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

_DESCRIPTION = """\
Estimate an object's pose with the paper's probabilistic model: a scene field from the RGB-D
frame, an object model, a classifier p_O (the frame's segmentation, or with --classifier
best-buddies the paper's best-buddy similarity inside the object's 2-D box), eq. (2) solved as a
weighted TLS problem (max-clique pruning + GNC, certified when a certifier is installed) and
refined on eq. (1). Prints T_camera_object (maps object-model points into the camera frame),
its eq. (1) log-likelihood, the eq. (2) certificate and, when the frame has ground truth, the
errors (translation, symmetry-axis angle, ADD-S).

examples:
  certpose pose --demo
  certpose pose --ycbv ../shared/data/ycbv --frame 0000/000001 --object 025_mug \\
      --model ../shared/data/ycbv/models/025_mug/points.xyz --json pose.json
  certpose pose --ycbv ../shared/data/ycbv --frame 0050/000001 --object 006_mustard_bottle \\
      --classifier best-buddies --object-model mustard_0002.npz   # no mask: box.txt + best buddies
  certpose pose --rgbd color.png depth.png --intrinsics 615.0 615.0 320.0 240.0 \
      --depth-scale 1000 --mask mug_mask.png --model mug.ply   # your own camera's frame
  certpose pose --demo --samples 10000 --particles mug.npz --plot mug.png
  certpose pose --demo --samples 10000 --method de --plot mug_de.png   # the paper's sampler
  certpose pose --ycbv ../shared/data/ycbv --frame 0000/000001 0000/000002 \\
      --object 025_mug 040_large_marker --json poses.json   # 4 pairs, one process

Several --frame and/or --object values pose every (frame, object) pair in one process (frames
outer), sparing the start-up and the kernel loading of one call per pair: each pair's block is
printed under a header line naming it, a pair whose object the frame does not list is skipped
with a message, and --json writes a LIST of the per-pair payloads (one payload, as for a single
pair, otherwise). The exit code is 1 only when no pair succeeded. --model, --object-model,
--box, --save-problem, --particles and --plot concern one pair and refuse several.
"""


def add_parser(subparsers: Any) -> None:
    from certpose.cli import add_common

    p = subparsers.add_parser(
        "pose",
        help="estimate an object pose from an RGB-D frame (YCB-Video, --rgbd files, or --demo)",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--demo", action="store_true",
                     help="the embedded synthetic scene: a textureless mug, handle hidden")
    src.add_argument("--ycbv", metavar="DIR", help="YCB-Video folder (with <scene>/ and models/)")
    src.add_argument("--rgbd", nargs=2, metavar=("COLOR", "DEPTH"), default=None,
                     help="your own RGB-D frame: a colour image ('-': none, geometry-only models) "
                          "and a one-channel depth image of the same size (with --intrinsics, "
                          "--model or --object-model, and --mask or --classifier best-buddies "
                          "--box)")
    from certpose.cli.bop import add_pose_options

    add_pose_options(p, src)  # --bop DIR and its options
    own = p.add_argument_group("your own RGB-D frame (--rgbd)")
    own.add_argument("--intrinsics", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                     default=None, help="the depth camera's pinhole intrinsics, pixels")
    own.add_argument("--depth-scale", type=float, default=None, metavar="S",
                     help="raw depth units per metre (default: 1000, millimetre PNGs)")
    own.add_argument("--mask", metavar="MASK.png", default=None,
                     help="the object's segmentation, same size (non-zero: object); or use "
                          "--classifier best-buddies --box instead")
    p.add_argument("--frame", metavar="SCENE/FRAME", nargs="+", default=None,
                   help="YCB-Video frame(s) (default: 0000/000001); with several frames or "
                        "objects, every pair is posed and --json writes a list of payloads")
    p.add_argument("--object", metavar="NAME", nargs="+", default=None,
                   help="YCB-Video object name(s) (default: 025_mug)")
    p.add_argument("--model", metavar="POINTS", default=None,
                   help="object model points, metres (default: DIR/models/NAME/points.xyz); the "
                        "model built from them is kept in $CERTPOSE_CACHE_DIR (default "
                        "~/.cache/certpose; set it empty to turn the cache off)")
    p.add_argument("--object-model", metavar="MODEL.npz", default=None,
                   help="object model with appearance from `certpose object build` (default: "
                        "geometry only, from the model points); the scene is described with its "
                        "descriptors")
    p.add_argument("--classifier", choices=("mask", "best-buddies"), default="mask",
                   help="p_O, the probability that a voxel belongs to the object: the frame's "
                        "segmentation (label.png, default), or best-buddy similarity between the "
                        "object model's descriptors and the scene's inside the object's 2-D box "
                        "(box.txt, what a detector gives; no mask is read)")
    p.add_argument("--box", type=float, nargs=4, metavar=("X0", "Y0", "X1", "Y1"), default=None,
                   help="with --classifier best-buddies: the object's box in pixels (x = column, "
                        "y = row) instead of the frame's box.txt")
    p.add_argument("--box-margin", type=float, default=None, metavar="PX",
                   help="with --classifier best-buddies: pixels added on every side of the box "
                        "(default: 0)")
    p.add_argument("--voxel-size", type=float, default=0.005, metavar="M",
                   help="scene/object voxel size in metres (default: 0.005)")
    p.add_argument("--free-space", choices=("voxels", "pixels"), default=None,
                   help="where eq. (1) reads observed free space: the scene grid's EMPTY voxels or "
                        "each pixel of the depth image (LikelihoodParams.free_space; default: "
                        "the library's)")
    p.add_argument("--revolution", action="store_true",
                   help="geometry-only model: sample a surface of revolution (a can, a mug's body) "
                        "with its symmetry, so that eq. (1) is flat along a turn about its axis "
                        "(object_from_points revolution='auto'; not the default: certpose.geometry.revolution has the figures)")
    p.add_argument("--no-certify", action="store_true", help="skip the eq. (2) certificate")
    p.add_argument("--require-certificate", action="store_true",
                   help="exit with code 1 unless the eq. (2) solution is certified")
    p.add_argument("--certify-modes", type=float, nargs="?", const=10.0, default=None,
                   metavar="SECONDS",
                   help="also certify eq. (2)'s mode set: every pose whose eq. (2) cost is within "
                        "--mode-margin of the best lies in the listed regions (a branch and bound "
                        "over rotations x translations; SECONDS: its time limit, default 10)")
    p.add_argument("--mode-margin", type=float, default=0.02, metavar="FRACTION",
                   help="with --certify-modes: the margin, a fraction of the best cost "
                        "(default: 0.02)")
    p.add_argument("--save-problem", metavar="FILE.npz", default=None,
                   help="write the eq. (2) problem (scene frame, metres; ground truth "
                        "T_scene_object when the frame has one) as a problem file for "
                        "`certpose register --problem` and `certpose bench --problems`")
    smp = p.add_argument_group("pose distribution (importance sampler seeded by the MLE and eq. (2))")
    smp.add_argument("--samples", type=int, default=0, metavar="N",
                     help="sample the pose distribution and keep N resampled particles")
    smp.add_argument("--particles", metavar="OUT.npz", default=None,
                     help="write the particles (rotations, translations, weights; T_camera_object)")
    smp.add_argument("--plot", metavar="OUT.png", default=None,
                     help="plot the marginals (roll, pitch, yaw, x, y, z and, for a mug, the "
                          "rotation about its axis; the ground truth when known)")
    smp.add_argument("--axis", type=float, nargs=3, metavar=("AX", "AY", "AZ"), default=None,
                     help="the object's symmetry axis (object frame) for each mode's turn and the "
                          "plot's turn-about-axis panel (default: the demo mug's, YCB-Video's "
                          "known ones; none for --rgbd)")
    smp.add_argument("--method", choices=("is", "de", "mcmc", "calibrated"), default="is",
                     help="is: the importance sampler (default); de: Nevergrad TwoPointsDE with "
                          "its population weighted (the paper's sampler); mcmc: random-walk "
                          "Metropolis on SE(3). The baselines get the same target and number of "
                          "eq. (1) evaluations. calibrated: exact draws of the calibrated "
                          "distribution (eq. (1)'s basins and flips, a model-error kernel; docs/concepts.md)")
    smp.add_argument("--model-error-tilt", default=None, metavar="DEG | iso",
                     help="for a model with an axis of revolution, split the kernel's rotation "
                          "into a tilt of DEG degrees across the axis and a spin of the kernel's "
                          "rotation about it; iso: the same kernel for every model "
                          "(PoseParams.model_error_tilt; default 0)")
    smp.add_argument("--axis-tilt-scale", type=float, default=None, metavar="S",
                     help="for a model with an axis of revolution, scale the sampled tilt across "
                          "the axis by S >= 0 about each basin's mean axis (PoseParams."
                          "axis_tilt_scale; 1: as sampled)")
    smp.add_argument("--temperature-scale", type=float, default=None, metavar="S",
                     help="multiply the importance sampler's default temperature rule (N / n_eff) "
                          "by S > 0 (default 1; ISParams.temperature_scale)")
    smp.add_argument("--model-error", nargs="+", metavar="DEG MM | fit", default=None,
                     help="the model-error kernel the distribution is convolved with (a Student t "
                          "with 5 degrees of freedom): DEG MM fixes its rotation (degrees) and "
                          "translation (millimetres) standard deviations per axis (default 2 2; "
                          "0 0: the bare distribution); 'fit' scales it by the measured depth "
                          "misfit of the posed model (PoseParams.model_error)")
    add_common(p, seed_help="random seed (default: 0)")
    p.set_defaults(func=run)


def _model_error_tilt_arg(value: str) -> float | str:
    """``--model-error-tilt``: ``iso`` or a non-negative number of degrees."""
    from certpose.cli import CLIError

    if value.strip().lower() == "iso":
        return "iso"
    try:
        deg = float(value)
    except ValueError:
        raise CLIError(f"--model-error-tilt must be a number of degrees or iso, got {value!r}") from None
    if not (math.isfinite(deg) and deg >= 0):
        raise CLIError(f"--model-error-tilt must be a non-negative number of degrees, got {value}")
    return deg


def _model_error_arg(values: list[str]) -> str | tuple[float, float]:
    """``--model-error``'s words as ``"fit"`` or ``(degrees, millimetres)``."""
    from certpose.cli import CLIError

    if values == ["fit"]:
        return "fit"
    try:
        nums = tuple(float(v) for v in values)
    except ValueError:
        nums = ()
    if len(nums) != 2 or not all(math.isfinite(v) and v >= 0 for v in nums):
        raise CLIError("--model-error must be 'fit' or two non-negative numbers (degrees, millimetres), "
                       f"got {' '.join(values)}")
    return nums  # type: ignore[return-value]


def _fmt(x: float | None, scale: float = 1.0, unit: str = "", digits: int = 2) -> str:
    if x is None or not math.isfinite(x):
        return "n/a"
    return f"{x * scale:.{digits}f}{unit}"


def kernels(argv: list[str]) -> tuple[str, ...]:
    """The compiled kernels of eq. (1), the eq. (2) solve and its certificate, and the scene's
    FPFH: on a first run they compile meanwhile (read from the raw arguments). Longest
    compilations first: the warm-up's helper takes the front, the command the back. The FPFH's
    are deferred (the helper compiles them last; until they are, the scene's FPFH is open3d's,
    the same numbers) and last: a warm cache is preloaded from the back, and the scene needs
    them first."""
    from solvers.certify import CERTIFY_KERNELS
    from solvers.registration import PRUNED_SOLVE_KERNELS

    certify = () if "--no-certify" in argv else CERTIFY_KERNELS
    if any(a == "--certify-modes" or a.startswith("--certify-modes=") for a in argv):
        from solvers.certify.mode_set import MODE_SET_KERNELS

        certify = (*certify, *MODE_SET_KERNELS)
    samples = ("certpose.sampling._kernels:mixture_log_densities",) \
        if any(a == "--samples" or a.startswith("--samples=") for a in argv) else ()
    return (PRUNED_SOLVE_KERNELS[0], *certify, "solvers.registration._kernels:max_clique_bnb",
            *PRUNED_SOLVE_KERNELS[1:], "solvers._linalg_kernels:rotvec_matrices", *samples,
            "certpose.model._kernels:eq1_batch", "certpose.geometry._fpfh_kernels:fpfh",
            "certpose.geometry._fpfh_kernels:normals_towards")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from certpose.cli import CLIError, busy, check_json_output, emit_json, say
    from certpose.cli.bop import check_pose_options, run_pose
    from certpose.estimation.mle import MLEParams
    from certpose.estimation.pipeline import PoseParams, run_demo
    from certpose.io.output import check_output_path

    check_pose_options(args)
    if args.bop is not None:
        if args.certify_modes is not None or args.mode_margin != 0.02:
            raise CLIError("--certify-modes/--mode-margin concern one pose's eq. (2) problem, "
                           "not --bop")
        return run_pose(args)
    check_json_output(args)
    if args.demo:
        # The demo is its own scene and model: YCB-Video's options would be silently ignored.
        given = [f"--{opt.replace('_', '-')}" for opt in ("frame", "object", "model", "object_model")
                 if getattr(args, opt) is not None]
        if given:
            raise CLIError(f"{'/'.join(given)} {'need' if len(given) > 1 else 'needs'} --ycbv "
                           "(--demo poses its own synthetic mug)")
    own = [f"--{opt.replace('_', '-')}" for opt in ("intrinsics", "depth_scale", "mask")
           if getattr(args, opt) is not None]
    if own and args.rgbd is None:
        raise CLIError(f"{'/'.join(own)} {'need' if len(own) > 1 else 'needs'} --rgbd "
                       "COLOR DEPTH")
    if args.rgbd is not None:
        if args.frame is not None:
            raise CLIError("--frame needs --ycbv (--rgbd gives the frame's images)")
        if args.object is not None and len(args.object) > 1:
            raise CLIError("--rgbd poses one object: give one --object name")
        if args.intrinsics is None:
            raise CLIError("--rgbd needs --intrinsics FX FY CX CY")
        if (args.model is None) == (args.object_model is None):
            raise CLIError("--rgbd needs one of --model POINTS and --object-model MODEL.npz")
        if args.classifier == "mask" and args.mask is None:
            raise CLIError("--rgbd needs --mask MASK.png, or --classifier best-buddies with --box")
        if args.classifier == "best-buddies" and (args.box is None or args.mask is not None):
            raise CLIError("--classifier best-buddies with --rgbd needs --box X0 Y0 X1 Y1 "
                           "(and no --mask)")
        for opt, path in [("model", args.model), ("object-model", args.object_model),
                          ("mask", args.mask), ("rgbd", args.rgbd[0]), ("rgbd", args.rgbd[1])]:
            if path is not None and path != "-" and not Path(path).is_file():
                raise CLIError(f"--{opt} {path} does not exist")
        if args.rgbd[1] == "-":
            raise CLIError("--rgbd: the depth image is needed ('-' stands for no colour image only)")
        if args.depth_scale is not None and not (math.isfinite(args.depth_scale)
                                                 and args.depth_scale > 0):
            raise CLIError(f"--depth-scale must be positive, got {args.depth_scale}")
    rgbd_name = args.object  # a user's frame has no default object (YCB-Video's is the mug)
    args.frame = args.frame or ["0000/000001"]
    args.object = args.object or ["025_mug"]
    pairs = [(f, o) for f in args.frame for o in args.object]  # frames outer
    if len(pairs) > 1:
        for opt in ("model", "object_model", "box", "save_problem", "particles", "plot"):
            if getattr(args, opt) is not None:
                raise CLIError(f"--{opt.replace('_', '-')} concerns one pair: it cannot combine "
                               f"with {len(pairs)} (frame, object) pairs")
    if args.require_certificate and args.no_certify:
        raise CLIError("--require-certificate and --no-certify exclude each other")
    if args.save_problem is not None:
        if not args.save_problem.endswith(".npz"):
            raise CLIError(f"--save-problem {args.save_problem} must end in .npz")
        check_output_path(args.save_problem, what="--save-problem output", force=args.force)
    if args.samples < 0:
        raise CLIError(f"--samples must be >= 0, got {args.samples}")
    if args.particles is not None:
        if args.samples == 0:
            raise CLIError("--particles needs --samples N")
        if not args.particles.endswith(".npz"):  # NumPy would append .npz to another name
            raise CLIError(f"--particles {args.particles} must end in .npz")
        check_output_path(args.particles, what="--particles output", force=args.force)
    if args.plot is not None:
        if args.samples == 0:
            raise CLIError("--plot needs --samples N")
        check_output_path(args.plot, what="--plot output", force=args.force)
        _check_plot_format(args.plot)
    if args.method != "is" and args.samples == 0:
        raise CLIError("--method needs --samples N")
    for flag in ("--model-error-tilt", "--axis-tilt-scale", "--temperature-scale", "--model-error"):
        if getattr(args, flag[2:].replace("-", "_")) is not None and args.samples == 0:
            raise CLIError(f"{flag} needs --samples N")
    if args.model_error_tilt is not None:
        args.model_error_tilt = _model_error_tilt_arg(args.model_error_tilt)
    if args.axis_tilt_scale is not None and not (math.isfinite(args.axis_tilt_scale) and args.axis_tilt_scale >= 0):
        raise CLIError(f"--axis-tilt-scale must be a non-negative number, got {args.axis_tilt_scale}")
    if args.temperature_scale is not None and not (math.isfinite(args.temperature_scale)
                                                   and args.temperature_scale > 0):
        raise CLIError(f"--temperature-scale must be a positive number, got {args.temperature_scale}")
    if args.model_error is not None:
        args.model_error = _model_error_arg(args.model_error)
    if args.axis is not None:
        if args.samples == 0:
            raise CLIError("--axis needs --samples N (it names the turn the modes and the plot show)")
        if not (all(math.isfinite(v) for v in args.axis) and any(v != 0 for v in args.axis)):
            raise CLIError(f"--axis must be a non-zero finite direction, got {args.axis}")
    if not (math.isfinite(args.voxel_size) and args.voxel_size > 0):
        raise CLIError(f"--voxel-size must be positive, got {args.voxel_size}")
    boxed = args.classifier == "best-buddies"
    if not boxed and (args.box is not None or args.box_margin is not None):
        raise CLIError("--box and --box-margin need --classifier best-buddies")
    if boxed and args.demo:
        raise CLIError("--classifier best-buddies needs --ycbv (the demo has no 2-D box)")
    if args.box_margin is not None and not (math.isfinite(args.box_margin) and args.box_margin >= 0):
        raise CLIError(f"--box-margin must be >= 0 pixels, got {args.box_margin}")
    if args.revolution and (args.demo or args.object_model is not None):
        raise CLIError("--revolution applies to geometry-only models from model points "
                       "(not --object-model; --demo models its mug with the symmetry already)")
    params = PoseParams(voxel_size=args.voxel_size, model_revolution=args.revolution)
    if args.box_margin is not None:
        params = replace(params, classifier=replace(params.classifier, box_margin=args.box_margin))
    if args.free_space is not None:
        params = replace(params, likelihood=replace(params.likelihood, free_space=args.free_space))
    if args.no_certify:
        params = replace(params, mle=replace(MLEParams(), certify=False))
    if args.certify_modes is not None:
        from solvers.certify.mode_set import ModeSetParams

        if not (math.isfinite(args.certify_modes) and args.certify_modes > 0):
            raise CLIError(f"--certify-modes must be a positive number of seconds, got "
                           f"{args.certify_modes}")
        if not (math.isfinite(args.mode_margin) and args.mode_margin >= 0):
            raise CLIError(f"--mode-margin must be >= 0, got {args.mode_margin}")
        params = replace(params, mode_set=ModeSetParams(margin=args.mode_margin,
                                                        time_limit=args.certify_modes))
    elif args.mode_margin != 0.02:
        raise CLIError("--mode-margin needs --certify-modes")
    if args.samples:
        from certpose.sampling.sampler import ISParams

        scale = 1.0 if args.temperature_scale is None else args.temperature_scale
        params = replace(params, sampler=ISParams(draws=max(10_000, args.samples),
                                                  resample=args.samples, temperature_scale=scale),
                         sampling_method=args.method)
        if args.model_error == "fit":
            params = replace(params, model_error="fit")
        elif args.model_error is not None:
            deg, mm = args.model_error
            params = replace(params, model_error=None if deg == mm == 0 else (math.radians(deg), mm / 1000.0))
        if args.model_error_tilt == "iso":
            params = replace(params, model_error_tilt=None)
        elif args.model_error_tilt is not None:
            params = replace(params, model_error_tilt=math.radians(args.model_error_tilt))
        if args.axis_tilt_scale is not None:
            params = replace(params, axis_tilt_scale=args.axis_tilt_scale)
    if args.rgbd is not None:
        return _run_rgbd(argparse.Namespace(**{**vars(args), "object": rgbd_name}), params)
    if args.demo:
        title = "synthetic mug scene (handle hidden behind an occluder)"
        with busy(args, "certpose pose"):
            from certpose.io.cache import default_cache_dir

            result = run_demo(params=params, rng=args.seed, cache_dir=default_cache_dir())
        one = _for_pair(args, args.frame[0], args.object[0])
        code, payload = _report(one, params, title, result)
        if args.json is not None:
            emit_json(args, payload)
        return code
    root = Path(args.ycbv)
    if not root.is_dir():
        raise CLIError(f"--ycbv {root} is not a directory")
    if args.model is not None and not Path(args.model).is_file():
        raise CLIError(f"--model {args.model} does not exist")
    if len(pairs) == 1:
        one = _for_pair(args, args.frame[0], args.object[0])
        try:
            code, payload = _pose_pair(one, params, root)
        except KeyError as exc:
            raise CLIError(str(exc.args[0]) if exc.args else str(exc)) from exc
        if args.json is not None:
            emit_json(args, payload)
        return code
    for frame in args.frame:  # bad input before any work
        if not (root / f"{frame}-meta.mat").is_file():
            raise CLIError(f"--frame {frame}: {root / (frame + '-meta.mat')} does not exist")
    payloads, codes = [], []
    for k, (frame, obj) in enumerate(pairs, 1):
        one = _for_pair(args, frame, obj)
        say(args, f"== pair {k}/{len(pairs)}: frame {frame}, object {obj} ==")
        try:
            with busy(args, f"certpose pose {k}/{len(pairs)}"):
                code, payload = _pose_pair(one, params, root, progress=False)
        except (KeyError, ValueError) as exc:  # e.g. an object the frame's meta.mat does not list
            msg = str(exc.args[0]) if exc.args else str(exc)
            sys.stdout.flush()  # the message lands between the blocks it concerns
            print(f"certpose pose: skipped {frame} {obj}: {msg}", file=sys.stderr)
            continue
        payloads.append(payload)
        codes.append(code)
    if args.json is not None:
        emit_json(args, payloads)
    say(args, f"posed {codes.count(0)} of {len(pairs)} pairs successfully"
              + (f" ({len(pairs) - len(codes)} skipped)" if len(codes) < len(pairs) else ""))
    sys.stdout.flush()
    return 0 if 0 in codes else 1


def _run_rgbd(args: argparse.Namespace, params: Any) -> int:
    """Pose one object in the user's own RGB-D frame (``--rgbd COLOR DEPTH``)."""
    from certpose.cli import busy, emit_json
    from certpose.estimation.pipeline import run_rgbd
    from certpose.io.cache import default_cache_dir

    color, depth = args.rgbd
    built = None
    if args.object_model is not None:
        from certpose.geometry.appearance import BuiltObjectModel

        built = BuiltObjectModel.load(args.object_model)
    name = (args.object[0] if args.object else
            built.model.name if built is not None and built.model.name else None)
    boxed = args.classifier == "best-buddies"
    title = f"{name or 'the object of ' + str(args.model or args.object_model)} in {depth}"
    if boxed:
        title += ", best buddies in the box given (no mask)"
    if built is not None:
        title += f" (appearance model from {', '.join(built.views) or 'unnamed views'})"
    with busy(args, "certpose pose"), _cli_hints():
        result = run_rgbd(None if color == "-" else color, depth, args.intrinsics,
                          model_path=args.model, object_model=built,
                          depth_scale=1000.0 if args.depth_scale is None else args.depth_scale,
                          mask_path=args.mask, box=args.box, name=name or "", params=params,
                          rng=args.seed, cache_dir=default_cache_dir())
    code, payload = _report(_for_pair(args, None, name), params, title, result)
    if args.json is not None:
        emit_json(args, payload)
    return code


@contextlib.contextmanager
def _cli_hints() -> Iterator[None]:
    """The library's advice in the command's own options: the scene grid's "crop with `bounds`
    or `roi_mask`" names keyword arguments the command line does not have."""
    from certpose.cli import CLIError

    try:
        yield
    except ValueError as exc:
        text = str(exc)
        if "max_voxels" in text:
            fix = "use a larger --voxel-size (metres) or a tighter --mask / --box"
        elif "too coarse" in text:
            fix = "use a smaller --voxel-size (metres)"
        else:
            raise
        raise CLIError(
            f"{text.split(';')[0]}; check --depth-scale (raw units per metre: 1000 for "
            f"millimetres, 10000 for YCB-Video) and --intrinsics, or {fix}") from exc


def _check_plot_format(path: str) -> None:
    """Refuse a --plot file type matplotlib cannot write before the work, not after it."""
    from certpose.cli import CLIError

    try:
        from matplotlib.backend_bases import FigureCanvasBase
    except ImportError:  # plot_marginals names the missing extra
        return
    suffix = Path(path).suffix.lower().lstrip(".")
    formats = FigureCanvasBase.get_supported_filetypes()
    if suffix not in formats:
        raise CLIError(f"--plot {path}: unsupported image type {suffix or '(none)'!r}; use one of "
                       f"{', '.join(sorted(formats))}")


def _for_pair(args: argparse.Namespace, frame: str, obj: str) -> argparse.Namespace:
    """``args`` with the one (frame, object) pair that a pose block concerns."""
    return argparse.Namespace(**{**vars(args), "frame": frame, "object": obj})


def _pose_pair(args: argparse.Namespace, params: Any, root: Path, *,
               progress: bool = True) -> tuple[int, dict[str, Any] | None]:
    """Pose ``args.object`` in the YCB-Video frame ``args.frame`` and print its block; the exit
    code of this pair and its --json payload (``None`` without --json)."""
    import contextlib

    from certpose.cli import CLIError, busy
    from certpose.estimation.pipeline import run_ycbv
    from certpose.io.cache import default_cache_dir

    boxed = args.classifier == "best-buddies"
    title = f"YCB-Video {args.frame}, {args.object}"
    if boxed:
        title += (", best buddies in the box " + ("given" if args.box is not None
                                                  else "of box.txt") + " (no mask)")
    built = None
    if args.object_model is not None:
        from certpose.geometry.appearance import BuiltObjectModel

        if not Path(args.object_model).is_file():
            raise CLIError(f"--object-model {args.object_model} does not exist")
        built = BuiltObjectModel.load(args.object_model)
        if built.model.name and built.model.name != args.object:
            raise CLIError(f"--object-model {args.object_model} is a model of "
                           f"{built.model.name}, not of --object {args.object}")
        title += f" (appearance model from {', '.join(built.views) or 'unnamed views'})"
    with busy(args, "certpose pose") if progress else contextlib.nullcontext():
        result = run_ycbv(root, args.frame, args.object, args.model, params=params,
                          rng=args.seed, object_model=built,
                          classifier="best_buddies" if boxed else "mask", box=args.box,
                          cache_dir=default_cache_dir())
    return _report(args, params, title, result)


def _report(args: argparse.Namespace, params: Any, title: str,
            result: Any) -> tuple[int, dict[str, Any] | None]:
    """Print one pair's block (and write its --save-problem/--particles/--plot files); its exit
    code and --json payload (``None`` without --json)."""
    from certpose.cli import say

    say(args, f"pose of {title}")
    say(args, f"status: {result.status} ({'success' if result.success else 'FAILED'})")
    say(args, "T_camera_object =")
    for row in result.T_camera_object:
        say(args, "  [" + "  ".join(f"{v: .6f}" for v in row) + "]")
    say(args, f"eq. (1) log-likelihood: {result.log_likelihood:.2f} (winning hypothesis: "
          f"{result.hypothesis})")
    say(args, f"eq. (2) minimiser on eq. (1): {_fmt(result.eq2_log_likelihood)} "
          f"({_fmt(result.eq2_refined_log_likelihood)} after refinement)")
    # The certificate bounds eq. (2) at its minimiser; say so, and whether that is this pose.
    say(args, f"certificate: {result.certificate_scope}")
    if result.mode_set is not None:
        _print_mode_set(args, result.mode_set, result.certificate)
    if len(result.modes) > 1:
        say(args, f"competing modes of eq. (1) (within {params.mle.mode_window:g} tempered nats of the best; "
              "eq. (1) barely tells them apart):")
        for k, m in enumerate(result.modes):
            err = m.get("errors")
            extra = "" if err is None else (f", vs ground truth: rotation "
                                             f"{_fmt(err['rotation_deg'], 1, ' deg', 1)}, ADD "
                                             f"{_fmt(err['add'], 100, ' cm')}")
            say(args, f"  {k}: eq. (1) {m['log_likelihood']:.2f} "
                  f"({m['log_likelihood'] - result.log_likelihood:+.2f}), rotation "
                  f"{m['rotation_from_best_deg']:.1f} deg from the returned pose, "
                  f"origin {m['origin']}{extra}")
    if result.errors is not None:
        e = result.errors
        say(args, f"errors vs ground truth: translation {_fmt(e.translation, 100, ' cm')}, "
              f"symmetry axis {_fmt(e.symmetry_axis_deg, 1, ' deg', 1)}, "
              f"rotation {_fmt(e.rotation_deg, 1, ' deg', 1)}, ADD-S {_fmt(e.add_s, 100, ' cm')}, "
              f"ADD {_fmt(e.add, 100, ' cm')}")
    t = result.timings
    say(args, f"time: MLE {_fmt(t.get('mle'), 1, ' s')} (scene building "
          f"{_fmt(t.get('scene'), 1, ' s')}, object model {_fmt(t.get('object'), 1, ' s')})")
    say(args, f"details: {result.message}")
    if result.distribution is not None:
        _print_distribution(result, args)
    if args.save_problem is not None:
        from certpose.estimation.pipeline import eq2_problem_data
        from certpose.io.problems import save_problem

        meta = {"name": f"{args.object}@{args.frame}" if not args.demo else f"demo-s{args.seed}",
                "scene": title, "seed": args.seed}
        path = save_problem(args.save_problem, **eq2_problem_data(result, **meta))
        say(args, f"wrote {path} (the eq. (2) problem; ground truth "
                  f"{'included' if result.T_camera_object_gt is not None else 'unknown'})")
    payload = None
    if args.json is not None:
        # The demo has no YCB-Video frame or object (their defaults do not apply to it).
        rgbd = getattr(args, "rgbd", None)
        payload = {"input": {"demo": bool(args.demo), "ycbv": args.ycbv,
                             "frame": None if args.demo or rgbd else args.frame,
                             "object": None if args.demo else args.object, "model": args.model,
                             "object_model": args.object_model, "seed": args.seed,
                             "classifier": args.classifier, "box": args.box,
                             **({"rgbd": rgbd, "intrinsics": args.intrinsics,
                                 "depth_scale": args.depth_scale, "mask": args.mask}
                                if rgbd else {})},
                   **result.to_dict()}
    sys.stdout.flush()
    if not result.success:
        return 1, payload
    if args.require_certificate and not (result.certificate is not None
                                         and result.certificate.certified):
        print("certpose pose: --require-certificate: the eq. (2) solution is not certified "
              f"({result.certificate_message or 'no certificate'})", file=sys.stderr)
        return 1, payload
    return 0, payload


def _print_mode_set(args: argparse.Namespace, ms: Any, certificate: Any) -> None:
    """The eq. (2) mode set: what it proves, its regions (camera frame) and the minimiser's gap
    (the larger of the mode set's and the eq. (2) certificate's lower bounds: both bound the
    same problem)."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from certpose.cli import say
    from solvers.certificate import relative_gap

    lower, source = ms.lower_bound, "the mode set's"
    cert_lower = float("nan") if certificate is None else float(certificate.lower_bound)
    if math.isfinite(cert_lower) and cert_lower > lower:
        lower, source = cert_lower, "the certificate's"
    bound = (f"literature gap of the minimiser {relative_gap(ms.best_cost, lower):.3g} "
             f"({source} lower bound {lower:.6g}, best {ms.best_cost:.6g})")
    if not ms.success:
        say(args, f"eq. (2) mode set: not certified ({ms.status.value}: {ms.message}); {bound}; "
                  f"{ms.solve_time:.1f} s")
        return
    say(args, f"eq. (2) mode set: CERTIFIED: every pose of eq. (2) cost <= "
              f"{ms.best_cost + ms.margin:.6g} (best + {ms.margin:.4g}) lies in "
              f"{len(ms.regions)} region(s) (camera frame); {bound}; {ms.boxes_explored} boxes, "
              f"{ms.solve_time:.1f} s")
    for k, r in enumerate(ms.regions):
        rv = np.degrees(Rotation.from_matrix(r.rotation).as_rotvec())
        say(args, f"  region {k}: rotation within {np.degrees(r.rotation_radius):.2f} deg of "
                  f"rotvec ({rv[0]:.1f}, {rv[1]:.1f}, {rv[2]:.1f}) deg, translation within "
                  f"{100 * r.translation_half_width:.2f} cm (each axis) of ("
                  + ", ".join(f"{100 * v:.2f}" for v in r.translation)
                  + f") cm; eq. (2) cost {r.cost:.6g} at its centre")


def _mode_rotation(R_mode: object, result: object, axis: object) -> str:
    """How a mode's mean rotation differs from the returned pose (and the ground truth): the
    geodesic angle, and the turn about the object's symmetry axis when it has one, so that modes
    along an ambiguity (a hidden handle's arc, a box's flips) read as such."""
    import numpy as np

    from certpose.sampling.plots import axis_angles
    from solvers.lie import rotation_error_deg

    def angles(T_ref: object) -> str:
        text = f"{rotation_error_deg(R_mode, np.asarray(T_ref)[:3, :3]):.1f} deg"
        if axis is not None:
            turn = np.degrees(axis_angles(np.asarray(R_mode)[None], axis, T_ref)[0])
            text += f" ({turn:+.1f} about the axis)"
        return text

    text = f"rotation {angles(result.T_camera_object)} from the returned pose"  # type: ignore[attr-defined]
    gt = result.T_camera_object_gt  # type: ignore[attr-defined]
    return text if gt is None else text + f", {angles(gt)} from the truth"


def _print_distribution(result: object, args: argparse.Namespace) -> None:
    from certpose.cli import say

    dist, info = result.distribution, result.sampling  # type: ignore[attr-defined]
    k = info.get("pareto_k")
    method = {"is": "importance sampler", "de": "Nevergrad TwoPointsDE, population weighted",
              "mcmc": "random-walk Metropolis",
              "calibrated": "calibrated: basins x model error"}[info.get("method", "is")]
    ess_kind = {"mcmc": "bulk ESS of the chains", "calibrated": "independent draws"}.get(
        info.get("method"), "ESS of the weighted draws")
    say(args, f"pose distribution ({method}): {len(dist)} particles (T_camera_object), {ess_kind} "
          f"{info['ess']:.0f}, Pareto-k {_fmt(k, 1, '', 2)}, temperature {info['temperature']:.3g}, "
          + (f"{info['evaluations']} eq. (1) evaluations" if info.get("evaluations") is not None
             else "built") + f" in {info['seconds']:.2f} s; {info['message']}")
    kern = info.get("model_error")
    if kern:
        say(args, f"  model-error kernel ({kern['rule']}"
              + (f", depth misfit {1000 * kern['misfit']:.2f} mm over {kern['misfit_points']} points, "
                 f"lever arm {100 * kern['lever_arm']:.1f} cm" if "misfit" in kern else "")
              + "): "
              + (f"tilt {math.degrees(kern['tilt_sigma']):.2f} deg across the axis of revolution, spin "
                 if "tilt_sigma" in kern else "")
              + f"{math.degrees(kern['rotation_sigma']):.2f} deg, {1000 * kern['translation_sigma']:.2f} mm"
              f" per axis, Student t {kern['dof']:g} dof")
    if info.get("tilt_scale") is not None:
        say(args, f"  tilt across the axis of revolution scaled by {info['tilt_scale']:g} about each "
                  "basin's mean axis (PoseParams.axis_tilt_scale)")
    from certpose.estimation.pipeline import YCBV_SYMMETRY_AXES

    axis = (tuple(args.axis) if args.axis is not None else (0.0, 0.0, 1.0) if args.demo
            else None if getattr(args, "rgbd", None) else YCBV_SYMMETRY_AXES.get(args.object))
    for j, m in enumerate(dist.modes()[:5]):
        say(args, f"  mode {j}: mass {m.mass:.3f} ({m.num_particles} particles), "
              f"{_mode_rotation(m.rotation, result, axis)}, translation "
              f"[{', '.join(f'{v:.4f}' for v in m.translation)}] m")
    if args.particles is not None:
        dist.save(args.particles)  # atomic
        say(args, f"wrote {args.particles}")
    if args.plot is not None:
        from certpose.sampling.plots import plot_marginals

        gt = result.T_camera_object_gt  # type: ignore[attr-defined]
        what = ("demo mug" if args.demo else
                f"{Path(args.rgbd[1]).name} {args.object or ''}".rstrip() if getattr(args, "rgbd", None)
                else f"{args.frame} {args.object}")
        title = (f"{what}: {method}, "
                 f"{len(dist)} particles" + ("" if gt is None else ", ground truth in red"))
        arcs = None
        if args.demo:
            import numpy as np

            from certpose.data.synthetic import make_mug_scene

            # The demo's scene again (the same seed draws it first): its exact hidden arc.
            sc = make_mug_scene(rng=args.seed)
            if gt is not None and np.allclose(sc.T_camera_object, gt):
                arcs = sc.hidden_handle_arc(step=1.0).arcs
        plot_marginals(dist, args.plot, axis=axis, T_gt=gt, arcs=arcs, arcs_label="handle hidden",
                       T_ref=gt if gt is not None else result.T_camera_object,  # type: ignore[attr-defined]
                       title=title, notes=[f"{ess_kind.split(' of')[0]}: {info['ess']:.0f}",
                                           f"Pareto-k: {_fmt(k, 1, '', 2)}",
                                           f"temperature: {info['temperature']:.3g}",
                                           f"time: {info['seconds']:.2f} s"])
        say(args, f"wrote {args.plot}")
