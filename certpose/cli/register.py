"""``certpose register``: robust registration of corresponding point files (or a demo)."""

from __future__ import annotations

import argparse
import math
import time
from typing import Any

import numpy as np

from certpose.cli import busy

_EPILOG = """\
Point files: .npy (N, 3), .csv/.txt (3 columns, comma or whitespace, optional header), .xyz,
.ply, .pcd. Row k of SRC corresponds to row k of DST. Weights: .npy or .csv/.txt, shape (N,).
With --fpfh VOXEL, SRC and DST are two scans (any sizes): they are matched first, as TEASER++'s
FPFH example matches them (voxel downsampling, FPFH, mutual nearest neighbours), e.g.
  certpose register cloud_bin_0.ply cloud_bin_4.ply --fpfh 0.05 --noise-bound 0.05 --certify
"""


def add_parser(subparsers: Any) -> None:
    from certpose.cli import add_common

    p = subparsers.add_parser(
        "register",
        help="robustly register corresponding point sets (weighted TLS)",
        description="Estimate T_target_source from putative correspondences with outliers.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("source", nargs="?", metavar="SRC", help="source points file")
    p.add_argument("target", nargs="?", metavar="DST", help="target points file (same rows)")
    p.add_argument("--problem", metavar="FILE.npz", default=None,
                   help="a problem file (source, target, weights, noise bounds, optional ground "
                        "truth) instead of SRC DST; written by `certpose pose --save-problem`")
    p.add_argument("--noise-bound", type=float, metavar="B",
                   help="inlier noise bound beta, in the units of the points (required with "
                        "point files; overrides a problem file's bounds)")
    p.add_argument("--weights", metavar="W", help="per-correspondence weights file")
    p.add_argument("--fpfh", type=float, default=None, metavar="VOXEL",
                   help="SRC and DST are scans: match them by FPFH features at this voxel size "
                        "(metres; TEASER++'s example: 0.05) and register the matches")
    p.add_argument("--solver", choices=("gnc", "sdp"), default="gnc",
                   help="gnc (default) or sdp (the SDP relaxation, with its certificate)")
    p.add_argument("--certify", action="store_true", help="attach an optimality certificate")
    p.add_argument("--scope", choices=("auto", "full", "pruned", "rotation"), default=None,
                   help="problem the certificate bounds: auto = the full problem with --certify, "
                        "the rotation (TIM) subproblem with --solver sdp")
    p.add_argument("--prefer", choices=("certificate", "cost"), default=None,
                   help="with --certify when the full problem cannot be certified (real scans): "
                        "certificate (default) returns the rotation subproblem's certified "
                        "optimum even at a higher cost; cost never returns a costlier pose")
    p.add_argument("--tol", type=float, default=None,
                   help="gap tolerance of the certificate (default: 0.001)")
    p.add_argument("--time-limit", type=float, default=None, metavar="S",
                   help="seconds the certifier may spend (default: 120 per bound search)")
    p.add_argument("--prune", choices=("auto", "always", "never"), default=None,
                   help="max-clique pruning before GNC (default: auto)")
    p.add_argument("--require-certificate", action="store_true",
                   help="implies --certify; exit with code 1 unless the pose is certified")
    demo = p.add_argument_group("demo (a built-in synthetic problem with known ground truth)")
    demo.add_argument("--demo", action="store_true", help="run the demo instead of reading files")
    demo.add_argument("--demo-n", type=int, default=None, metavar="N",
                      help="correspondences in the demo (default: 100)")
    demo.add_argument("--demo-outliers", type=float, default=None, metavar="R",
                      help="outlier fraction in the demo (default: 0.8)")
    demo.add_argument("--demo-noise", type=float, default=None, metavar="SIGMA",
                      help="inlier noise std in the demo (default: 0.01; beta = 5.54 sigma)")
    add_common(p, seed_help="seed of the --demo instance (default: 0); the solvers are "
                            "deterministic",
               json_help="write the result (and inputs) as JSON to OUT ('-': standard output)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from certpose.cli import CLIError, check_json_output

    check_json_output(args)
    if args.require_certificate and args.solver == "gnc":
        args.certify = True
    if sum([bool(args.demo), args.problem is not None, bool(args.source or args.target)]) > 1:
        raise CLIError("give one of SRC DST, --problem FILE or --demo")
    _check_options(args)
    if args.demo:
        return _run_demo(args)
    if args.problem is not None:
        return _run_problem(args)
    if not args.source or not args.target:
        raise CLIError("SRC and DST point files are required (or use --demo)")
    if args.noise_bound is None:
        raise CLIError("--noise-bound B is required")

    from certpose.api import register
    from certpose.io.points import read_correspondences, read_weights

    if args.fpfh is None:
        source, target = read_correspondences(args.source, args.target)
        how = "correspondences"
    else:
        from certpose.data.threedmatch import scan_correspondences

        corr = scan_correspondences(args.source, args.target, voxel_size=args.fpfh)
        source, target = corr.source, corr.target
        how = f"FPFH correspondences (voxel {args.fpfh:g})"
    weights = None if args.weights is None else read_weights(args.weights, n=source.shape[0])
    with busy(args, "certpose register"):
        result = register(
            source, target, noise_bound=args.noise_bound, weights=weights, solver=args.solver,
            certify=args.certify, prune=args.prune, **_cert_options(args),
        )
    _say(args, f"certpose register: {source.shape[0]} {how}, {args.source} -> "
               f"{args.target}, noise bound {args.noise_bound:g}, solver {args.solver}")
    _say(args, _summary(result))
    if args.json:
        inputs = {
            "source": str(args.source), "target": str(args.target),
            "weights": None if args.weights is None else str(args.weights),
            "num_correspondences": int(source.shape[0]), "fpfh_voxel": args.fpfh,
            "noise_bound": args.noise_bound,
            "solver": args.solver, "certify": args.certify, "prune": args.prune,
        }
        _write_json(args, {"inputs": inputs, "result": result.to_dict()})
    return _exit_code(args, result)


def _check_options(args: argparse.Namespace) -> None:
    """Refuse options that the rest of the command line would silently ignore; then fill in
    their defaults."""
    from certpose.cli import CLIError

    given = [f"--{name.replace('_', '-')}" for name in ("scope", "tol", "time_limit", "prefer")
             if getattr(args, name) is not None]
    if given and not (args.certify or args.require_certificate or args.solver == "sdp"):
        raise CLIError(f"{'/'.join(given)} {'concern' if len(given) > 1 else 'concerns'} the "
                       "certificate: add --certify (or "
                       "--require-certificate, --solver sdp)")
    if args.prune is not None and args.solver == "sdp":
        raise CLIError("--prune applies to --solver gnc (the SDP relaxation does not prune)")
    demo = [f"--{name.replace('_', '-')}" for name in ("demo_n", "demo_outliers", "demo_noise")
            if getattr(args, name) is not None]
    if demo and not args.demo:
        raise CLIError(f"{'/'.join(demo)} {'set' if len(demo) > 1 else 'sets'} the --demo "
                       "problem: add --demo")
    if args.demo and args.weights is not None:
        raise CLIError("--weights does not apply to --demo (its weights are 1)")
    if args.fpfh is not None:
        if args.demo or args.problem is not None:
            raise CLIError("--fpfh matches the scans SRC DST: it does not apply to "
                           f"{'--demo' if args.demo else '--problem'}")
        if args.weights is not None:
            raise CLIError("--weights does not apply to --fpfh (the matches are not known "
                           "before matching)")
        if not (math.isfinite(args.fpfh) and args.fpfh > 0):
            raise CLIError(f"--fpfh must be a positive voxel size in metres, got {args.fpfh}")
    defaults = {"scope": "auto", "tol": 1e-3, "prune": "auto", "prefer": "certificate",
                "demo_n": 100, "demo_outliers": 0.8, "demo_noise": 0.01}
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    if args.demo:  # in the options' own names, not the generator's arguments
        if not args.demo_n >= 3:
            raise CLIError(f"--demo-n must be >= 3 correspondences, got {args.demo_n}")
        if not 0 <= args.demo_outliers < 1:
            raise CLIError(f"--demo-outliers must be a fraction in [0, 1), got {args.demo_outliers}")
        if not (math.isfinite(args.demo_noise) and args.demo_noise >= 0):
            raise CLIError(f"--demo-noise must be a finite sigma >= 0, got {args.demo_noise}")


def kernels(argv: list[str]) -> tuple[str, ...]:
    """The compiled kernels ``certpose register ARGV`` will call (read from the raw arguments:
    the warm-up starts before the parser is built)."""
    from solvers.certify import CERTIFY_KERNELS
    from solvers.registration import PRUNED_SOLVE_KERNELS

    sdp = any(a == "--solver=sdp" or (a == "--solver" and b == "sdp")
              for a, b in zip(argv, argv[1:] + [""], strict=True))
    certify = sdp or "--certify" in argv or "--require-certificate" in argv
    return PRUNED_SOLVE_KERNELS + (CERTIFY_KERNELS if certify else ())


def _run_problem(args: argparse.Namespace) -> int:
    from certpose.api import register
    from certpose.cli import CLIError
    from certpose.io.problems import load_problem

    prob = load_problem(args.problem)
    if args.weights is not None:
        raise CLIError("--weights does not apply to --problem (the file holds the weights)")
    beta = prob.noise_bound if args.noise_bound is None else args.noise_bound
    with busy(args, "certpose register"):
        result = register(
            prob.source, prob.target, noise_bound=beta, weights=prob.weights,
            solver=args.solver, certify=args.certify, prune=args.prune, **_cert_options(args),
        )
    bound = (f"{beta:g}" if np.ndim(beta) == 0
             else f"{np.min(beta):g}-{np.max(beta):g} (per correspondence)")
    meta = ", ".join(f"{k} {v}" for k, v in prob.metadata.items() if k in ("suite", "name"))
    _say(args, f"certpose register: {prob.n} correspondences from {args.problem}"
               f"{f' ({meta})' if meta else ''}, noise bound {bound}, solver {args.solver}")
    _say(args, _summary(result))
    errors = None
    if prob.T_target_source is not None:
        errors = _errors(result, prob.T_target_source[:3, :3], prob.T_target_source[:3, 3])
        _say(args, "ground truth T_target_source:\n" + _matrix(prob.T_target_source))
        _say(args, f"rotation error    : {errors['rotation_deg']:.4f} deg\n"
                   f"translation error : {errors['translation']:.5g}")
    if args.json:
        _write_json(args, {
            "inputs": {"problem": str(args.problem), "metadata": prob.metadata,
                       "num_correspondences": prob.n, "noise_bound": beta,
                       "solver": args.solver, "certify": args.certify, "prune": args.prune},
            "ground_truth": None if prob.T_target_source is None
            else {"T_target_source": prob.T_target_source.tolist()},
            "errors": errors,
            "result": result.to_dict(),
        })
    return _exit_code(args, result)


def _errors(result: Any, R: np.ndarray, t: np.ndarray) -> dict[str, float]:
    from solvers.lie import rotation_error_deg, translation_error

    return {"rotation_deg": rotation_error_deg(result.rotation, R),
            "translation": translation_error(result.translation, t)}


def _run_demo(args: argparse.Namespace) -> int:
    from certpose.api import register
    from certpose.data.instances import make_instance
    from certpose.io.points import synthetic_shape
    from solvers.lie import rotation_error_deg, translation_error

    inst = make_instance(synthetic_shape(), args.demo_n, args.demo_outliers,
                         noise=args.demo_noise, rng=args.seed)
    beta = inst.noise_bound if args.noise_bound is None else args.noise_bound
    with busy(args, "certpose register --demo"):
        register(inst.source, inst.target, noise_bound=beta)  # JIT warm-up, untimed
        t0 = time.perf_counter()
        result = register(inst.source, inst.target, noise_bound=beta, solver=args.solver,
                          certify=args.certify, prune=args.prune, **_cert_options(args))
        elapsed = time.perf_counter() - t0
    rot_err = rotation_error_deg(result.rotation, inst.rotation)
    trans_err = translation_error(result.translation, inst.translation)
    n_out = int(inst.outliers.sum())
    _say(args, f"certpose register --demo: synthetic shape, {args.demo_n} correspondences, "
               f"{n_out} outliers ({100 * n_out / args.demo_n:.0f}%), sigma {args.demo_noise:g}, "
               f"noise bound {beta:g}, seed {args.seed}")
    _say(args, _summary(result))
    T_gt = np.eye(4)
    T_gt[:3, :3], T_gt[:3, 3] = inst.rotation, inst.translation
    _say(args, "ground truth T_target_source:\n" + _matrix(T_gt))
    _say(args, f"rotation error    : {rot_err:.4f} deg\ntranslation error : {trans_err:.5f}\n"
               f"time              : {1e3 * elapsed:.3f} ms (after JIT warm-up)")
    if args.json:
        _write_json(args, {
            "inputs": {"demo": True, "n": args.demo_n, "outlier_ratio": args.demo_outliers,
                       "noise": args.demo_noise, "noise_bound": beta, "seed": args.seed,
                       "solver": args.solver, "certify": args.certify, "prune": args.prune},
            "ground_truth": {"T_target_source": T_gt.tolist()},
            "errors": {"rotation_deg": rot_err, "translation": trans_err},
            "result": result.to_dict(),
        })
    return _exit_code(args, result)


def _say(args: argparse.Namespace, text: str) -> None:
    from certpose.cli import say

    say(args, text)


def _exit_code(args: argparse.Namespace, result: Any) -> int:
    """0; 1 when the solve failed or --require-certificate is not met (said on stderr)."""
    import sys

    if not result.success:
        return 1
    if args.require_certificate:
        cert = result.certificate
        if cert is None or not cert.certified:
            why = "no certificate" if cert is None else (
                f"the certificate's gap {cert.relative_gap:.3g} exceeds tol {cert.tol:g}")
            print(f"certpose register: --require-certificate: the pose is not certified ({why})",
                  file=sys.stderr)
            return 1
    return 0


def _cert_options(args: argparse.Namespace) -> dict[str, Any]:
    return {"scope": args.scope, "tol": args.tol, "time_limit": args.time_limit,
            "prefer": args.prefer}


def _matrix(T: np.ndarray) -> str:
    return "\n".join("  [" + " ".join(f"{v:+.6f}" for v in row) + "]" for row in T)


def _summary(result: Any) -> str:
    n = result.inliers.shape[0]
    lines = [
        f"status            : {result.status.value} ({'success' if result.success else 'FAILED'})",
        f"message           : {result.message}",
        "T_target_source   :",
        _matrix(result.T_target_source),
        f"inliers           : {result.num_inliers} / {n}",
        f"cost              : {result.cost:.6g}",
        f"iterations        : {result.iterations}",
        f"solve time        : {1e3 * result.solve_time:.3f} ms ({result.solver})",
    ]
    cert = result.certificate
    if cert is None:
        lines.append("certificate       : none (use --certify or --solver sdp)")
    else:
        lines.append(
            f"certificate       : {'CERTIFIED' if cert.certified else 'not certified'} for "
            f"{cert.problem} ({cert.num_terms} terms, {cert.method}), gap {cert.relative_gap:.3e} "
            f"(tol {cert.tol:g}; literature gap {cert.literature_gap:.3e}), bounds "
            f"[{cert.lower_bound:.6g}, {cert.upper_bound:.6g}]; it covers the returned pose"
        )
        lines.append(f"                    {cert.message}")
        other = result.info.get("full_problem_certificate") or result.info.get(
            "rotation_certificate")
        if other is not None:
            gap = other.get("relative_gap")
            lines.append(f"also bounded      : {other['problem']}, "
                         f"{'CERTIFIED' if other['certified'] else 'not certified'}, gap "
                         f"{'n/a' if gap is None else f'{gap:.3e}'} (of the pose it was "
                         "computed for; see the message)")
    return "\n".join(lines)


def _write_json(args: argparse.Namespace, payload: dict[str, Any]) -> None:
    from certpose.cli import emit_json

    emit_json(args, payload)
