"""Calibration of the pose distribution on the shared YCB-Video frames.

For every visible (frame, object) pair of the given scenes, with the frame's ground-truth mask
as the classifier, the MLE is found once (cached with ``--cache DIR``: the seeds, the MLE and the
truth's eq. (1) values), then the importance sampler is run at one or more temperatures and the
ground-truth pose's highest-density credible level is recorded: the truth lies inside the 90%
(50%) credible region when its level is <= 0.9 (0.5). A calibrated distribution puts it inside
the 90% region in 80-100% of pairs and inside the 50% region in 35-65% (the target).
Models: geometry-only (``points.xyz``) on every pair, and, with ``--appearance``, appearance models
built from the views of the *other* scene for the objects seen in two scenes (never evaluated on
the scene whose views built them).

Two levels per run: ``target`` ranks the draws by eq. (1) itself (the exact highest-density
region of ``exp(eq. (1) / T)``, :meth:`ISResult.credible_level`; the reported one) and ``kde`` by
a kernel density of the particles (:meth:`PoseDistribution.credible_level`; one kernel per
mode of the particles).

Temperatures. ``--scales`` multiplies the library's default rule
(:func:`certpose.sampling.sampler.default_temperature`); ``--fit SCENES`` instead fits the scale
of the rule ``temperature = scale * N / n_eff`` on the pairs of ``SCENES`` only (the gap-based
derivation of :func:`fit_scale`) and samples the *other* scenes at it (held out: never tuned on
the pairs it reports).

Symmetric objects (BOP's YCB-V list) have no single true pose: the truth's eq. (1) is taken at the
best of its equivalents under rotations about the model's z axis (every 10 deg) and a half turn
about x (stated, lenient), and they are reported apart. A run whose effective sample size is below
``MIN_ESS`` has no meaningful level and counts as outside.

usage::

    python examples/benchmarks/bench_calibration.py --appearance --cache calib-cache     # default temperature
    python examples/benchmarks/bench_calibration.py --appearance --cache calib-cache --fit 0000,0002
    python examples/benchmarks/bench_calibration.py --appearance --scales 0.5 1 2 4 --out calib.jsonl
    python examples/benchmarks/bench_calibration.py --appearance --cache calib-cache --calibrated --loso
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import time
from pathlib import Path

import numpy as np

SYMMETRIC = {"002_master_chef_can", "024_bowl", "036_wood_block", "040_large_marker",
             "051_large_clamp", "052_extra_large_clamp", "061_foam_brick"}
#: Objects seen in two scenes: an appearance model from one is tested on the other.
OTHER_SCENE = {("006_mustard_bottle", "0002"): "0050", ("006_mustard_bottle", "0050"): "0002",
               ("011_banana", "0002"): "0050", ("011_banana", "0050"): "0002",
               ("010_potted_meat_can", "0002"): "0049", ("010_potted_meat_can", "0049"): "0002"}
#: Fits whose training loss is within this of the best count as tied (the sharpest wins).
TIE = 0.03
#: Below this ESS a run's level means nothing (one particle carries the mass): counted outside.
MIN_ESS = 50.0


def _equivalents(T_gt: np.ndarray, symmetric: bool) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    if not symmetric:
        return T_gt[None]
    out = []
    for flip in (np.eye(3), Rotation.from_rotvec([np.pi, 0, 0]).as_matrix()):
        for a in np.radians(np.arange(0, 360, 10)):
            T = T_gt.copy()
            T[:3, :3] = T_gt[:3, :3] @ Rotation.from_rotvec([0, 0, a]).as_matrix() @ flip
            out.append(T)
    return np.stack(out)


def _frames(root: Path, scene: str) -> list[str]:
    return sorted(f"{scene}/{p.name[:6]}" for p in (root / scene).glob("*-meta.mat"))


def _rot_deg(A: np.ndarray, B: np.ndarray) -> float:
    c = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def _cache_path(cache: Path, frame: str, obj: str, kind: str) -> Path:
    return cache / f"{frame.replace('/', '-')}-{obj}-{kind}.pkl"


def prepare_pair(root: Path, frame: str, obj: str, object_model=None,  # noqa: ANN001
                 cache: Path | None = None, *, likelihood: bool = True) -> tuple:
    """The pair's likelihood and its MLE-side facts (seeds, eq. (1) at the MLE and at the truth),
    the latter read from / written to ``cache`` (the MLE is the slow part; the scene is rebuilt
    unless ``likelihood`` is False and the pair is cached: then the likelihood is None)."""
    kind = "appearance" if object_model is not None else "geometry"
    path = None if cache is None else _cache_path(cache, frame, obj, kind)
    if path is not None and path.exists() and not likelihood:
        with path.open("rb") as fh:
            return None, pickle.load(fh)
    from certpose.estimation.mle import estimate_mle, refine_pose
    from certpose.estimation.pipeline import PoseParams
    from certpose.geometry.features import FPFHBackbone
    from certpose.geometry.objects import object_from_points
    from certpose.io.ycbv import load_model_points, load_ycbv_frame
    from certpose.model.classifier import classify_from_mask
    from certpose.model.likelihood import PoseLikelihood
    from certpose.model.scene import build_scene_field
    from certpose.sampling.sampler import default_temperature, seeds_from_mle

    params = PoseParams()
    yf = load_ycbv_frame(root, frame)
    mask = yf.object_mask(obj)
    backbone = object_model.backbone if object_model is not None else FPFHBackbone()
    scene = build_scene_field(yf.frame, backbone, voxel_size=params.voxel_size, roi_mask=mask,
                              margin=params.roi_margin)
    if object_model is not None:
        model = object_model.model
    else:
        model = object_from_points(load_model_points(root / "models" / obj / "points.xyz"),
                                   backbone, voxel_size=params.voxel_size, name=obj)
    cls = classify_from_mask(scene, yf.frame.with_mask(mask), params=params.classifier)
    lik = PoseLikelihood(scene, cls, model, params=params.likelihood)
    if path is not None and path.exists():
        with path.open("rb") as fh:
            info = pickle.load(fh)
        return lik, info
    t = time.perf_counter()
    mle = estimate_mle(scene, cls, model, params=params.mle, likelihood_params=params.likelihood,
                       viewpoint=np.zeros(3), rng=0)
    t_mle = time.perf_counter() - t
    T_gt = yf.poses[obj]  # scene frame = camera frame for YCB-Video frames
    eqs = _equivalents(T_gt, obj in SYMMETRIC)
    l_eqs = lik(eqs)
    best = int(np.argmax(l_eqs))
    radius = float(np.linalg.norm(model.points - model.points.mean(0), axis=1).max())
    T_ref, l_ref, _ = refine_pose(lik, eqs[best], scale=radius)
    seeds = seeds_from_mle(mle)
    # Do the MLE's seeds contain the truth's basin? (the closest seed to the best equivalent)
    d_seed = min(_rot_deg(S, eqs[best]) for S in seeds)
    info = {
        "case": f"{frame} {obj}", "scene": frame.split("/")[0], "object": obj,
        "symmetric": obj in SYMMETRIC, "model": kind,
        "mle_rot_err_deg": round(_rot_deg(eqs[best], mle.T_scene_object), 2),
        "mle_trans_err_cm": round(float(100 * np.linalg.norm(mle.T_scene_object[:3, 3] - T_gt[:3, 3])), 3),
        "mle_s": round(t_mle, 2), "num_seeds": len(seeds), "closest_seed_rot_deg": round(d_seed, 2),
        "N": lik.total_weight, "T0": default_temperature(lik, seeds[0]),
        "eq1_mle": float(mle.log_likelihood), "eq1_truth": float(l_eqs[best]),
        "eq1_truth_refined": float(l_ref),
        "refined_truth_rot_deg": round(_rot_deg(eqs[best], T_ref), 2),
        "refined_truth_trans_cm": round(float(100 * np.linalg.norm(T_ref[:3, 3] - eqs[best][:3, 3])), 3),
        "seeds": seeds, "T_truth": eqs[best],
    }
    if path is not None:
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        with tmp.open("wb") as fh:
            pickle.dump(info, fh)
        tmp.replace(path)  # atomic: concurrent runs share a cache
    return lik, info


def sample_pair(lik, info: dict, temperatures: dict[str, float], draws: int) -> dict:  # noqa: ANN001
    """Sample the pair at each named temperature; the truth's levels (target and kde), ESS, time."""
    from certpose.sampling.sampler import ISParams, sample_pose_distribution

    row = {k: v for k, v in info.items() if k not in ("seeds", "T_truth")}
    row.update(levels={}, kde_levels={}, ess={}, sampling_s={}, temperature={})
    T = info["T_truth"]
    for name, temp in temperatures.items():
        res = sample_pose_distribution(lik, info["seeds"], params=ISParams(draws=draws, temperature=temp), rng=0)
        d = res.weighted
        row["levels"][name] = round(res.credible_level(info["eq1_truth"]), 4)
        row["kde_levels"][name] = round(d.credible_level(T[:3, :3], T[:3, 3], max_particles=min(draws, 2000)), 4)
        row["ess"][name] = round(d.ess, 1)
        row["sampling_s"][name] = round(res.seconds, 2)
        row["temperature"][name] = round(temp, 3)
    return row


def fit_scale(infos: list[dict], quantile: float = 0.5) -> float:
    """Scale ``c`` of the rule ``temperature = c * N / n_eff`` fitted on ``infos`` (training pairs).

    Near a maximum the target ``exp(eq. (1) / T)`` is about Gaussian in the 6-D tangent chart, so
    a pose ``g`` nats below the maximum lies on the boundary of the highest-density region of
    level ``chi2_6.cdf(2 g / T)``. Calibration asks the truth's level to be uniform, i.e. the
    truth's gaps ``g_i = eq1(MLE) - eq1(truth)`` to satisfy ``2 g_i / (c T0_i) ~ chi2_6``; the
    fitted ``c`` makes the training pairs' median level 0.5 (``quantile``):
    ``c = quantile_i(2 g_i / T0_i) / chi2_6.ppf(quantile)``. The gap is taken at the truth
    itself (not refined), so the annotation's own error is part of what the temperature covers.
    """
    from scipy.stats import chi2

    r = np.array([2.0 * max(i["eq1_mle"] - i["eq1_truth"], 0.0) / i["T0"] for i in infos])
    return float(np.quantile(r, quantile) / chi2.ppf(quantile, 6))


def pair_basins(lik, info: dict, cache: Path) -> object:  # noqa: ANN001
    """The pair's :class:`~certpose.sampling.calibration.Basins` (cached beside its MLE)."""
    from certpose.sampling.calibration import find_basins

    path = cache / (info["case"].replace("/", "-").replace(" ", "-") + f"-{info['model']}-basins.pkl")
    if path.exists():
        with path.open("rb") as fh:
            return pickle.load(fh)
    b = find_basins(lik, info["seeds"])
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    with tmp.open("wb") as fh:
        pickle.dump(b, fh)
    tmp.replace(path)
    return b


def calibrated_level(info: dict, basins, params, draws: int = 4000) -> float:  # noqa: ANN001
    """The truth's credible level (best equivalent) under the calibrated distribution."""
    from certpose.sampling.calibration import calibrated_distribution

    d = calibrated_distribution(None, basins=basins, params=params)
    return d.credible_level(_equivalents(info["T_truth"], info["symmetric"]), draws=draws)


def fit_calibration(pairs: list[tuple[dict, object]]):  # noqa: ANN201
    """:func:`certpose.sampling.calibration.fit_calibration` on training ``pairs`` (info, basins),
    the truth taken at its equivalents (symmetric objects): (params, right-basin pairs, table)."""
    from certpose.sampling.calibration import fit_calibration as fit

    res = fit([(b, _equivalents(info["T_truth"], info["symmetric"])) for info, b in pairs], tie=TIE)
    return res.params, res.num_right, res.table


def _level(row: dict, name: str, key: str = "levels") -> float:
    return row[key][name] if row["ess"][name] >= MIN_ESS else 1.0


def summarise(rows: list[dict], names: list[str], title: str = "") -> None:
    if title:
        print(f"\n{title}")
    print(f"{'pairs':<34} {'temperature':>18} {'in 90%':>7} {'in 50%':>7} {'kde 90%':>8} "
          f"{'kde 50%':>8} {'median lvl':>10} {'ESS<' + str(int(MIN_ESS)):>7} {'med ESS':>8}")
    groups = {
        "non-symmetric, geometry": [r for r in rows if not r["symmetric"] and r["model"] == "geometry"],
        "non-symmetric, appearance": [r for r in rows if not r["symmetric"] and r["model"] == "appearance"],
        "symmetric (best equivalent)": [r for r in rows if r["symmetric"]],
        "geometry-only models": [r for r in rows if r["model"] == "geometry"],
        "appearance models": [r for r in rows if r["model"] == "appearance"],
        **{f"scene {sc}": [r for r in rows if r["scene"] == sc] for sc in sorted({r["scene"] for r in rows})},
        "all": rows,
    }
    for gname, rs in groups.items():
        rs = [r for r in rs if all(n in r["levels"] for n in names)]
        if not rs:
            continue
        for n in names:
            lv = np.array([_level(r, n) for r in rs])
            kd = np.array([_level(r, n, "kde_levels") for r in rs])
            low = sum(r["ess"][n] < MIN_ESS for r in rs)
            temps = [r["temperature"][n] for r in rs]
            tdesc = f"{n} {np.min(temps):.0f}-{np.max(temps):.0f}"
            k90, k50 = ((f"{np.mean(kd <= 0.9):.2f}", f"{np.mean(kd <= 0.5):.2f}")
                        if np.all(np.isfinite(kd)) else ("-", "-"))
            print(f"{gname + f' ({len(rs)})':<34} {tdesc:>18} {np.mean(lv <= 0.9):>7.2f} "
                  f"{np.mean(lv <= 0.5):>7.2f} {k90:>8} {k50:>8} "
                  f"{np.median(lv):>10.3f} {low:>7d} {np.median([r['ess'][n] for r in rs]):>8.0f}")


def run_calibrated(args, jobs: list, infos: list[dict], fit_scenes: set[str]) -> None:  # noqa: ANN001
    """``--calibrated``: basins per pair (cached), parameters fitted on ``fit_scenes`` (or the
    library's defaults; with ``--loso`` each scene in turn is scored with the parameters fitted
    on the others), the held-out scenes' truth levels under the calibrated distribution."""
    from certpose.sampling.calibration import CalibrationParams

    pairs = []
    for (frame, obj, om), info in zip(jobs, infos, strict=True):
        b_path = args.cache / (info["case"].replace("/", "-").replace(" ", "-") + f"-{info['model']}-basins.pkl")
        lik = None if b_path.exists() else prepare_pair(args.data, frame, obj, om, args.cache)[0]
        pairs.append((info, pair_basins(lik, info, args.cache)))
    scenes = sorted({info["scene"] for info, _ in pairs})
    if args.loso:
        folds = [(set(scenes) - {sc}, {sc}) for sc in scenes]
    elif fit_scenes:
        folds = [(fit_scenes, set(scenes) - fit_scenes)]
    else:
        folds = [(set(), set(scenes))]
    name = "fit" if (fit_scenes or args.loso) else "default"
    rows = []
    for train, test in folds:
        if train:
            params, n_right, table = fit_calibration([pi for pi in pairs if pi[0]["scene"] in train])
            print(f"fitted on {sorted(train)} ({n_right} right-basin pairs for the model error): "
                  f"rotation_sigma {np.degrees(params.rotation_sigma):.2f} deg, translation_sigma "
                  f"{1000 * params.translation_sigma:.2f} mm, basin_temperature {params.basin_temperature:g}, "
                  f"dof {params.dof:g}", flush=True)
            for nu, tb, f90, f50 in table:
                print(f"  training pairs at dof {nu:g}, basin temperature {tb:g}: in 90% {f90:.2f}, in 50% {f50:.2f}")
        else:
            params = CalibrationParams()
        for info, b in pairs:
            if info["scene"] not in test:
                continue
            row = {k: v for k, v in info.items() if k not in ("seeds", "T_truth")}
            row.update(levels={name: round(calibrated_level(info, b, params), 4)}, kde_levels={name: np.nan},
                       ess={name: np.inf}, sampling_s={name: 0.0}, temperature={name: params.basin_temperature},
                       num_basins=len(b.poses), fitted_on=sorted(train))
            rows.append(row)
            print(json.dumps(row), flush=True)
            if args.out is not None:
                with open(args.out, "a") as fh:
                    fh.write(json.dumps(row) + "\n")
    how = ("held out, each scene fitted on the others" if args.loso else
           f"held out, fit on {args.fit}" if fit_scenes else "defaults")
    summarise(rows, [name], f"calibrated distribution ({how})")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    here = Path(__file__).resolve().parents[2]
    ap.add_argument("--data", type=Path, default=here.parent / "shared" / "data" / "ycbv")
    ap.add_argument("--scenes", default="0000,0002,0049,0050")
    ap.add_argument("--frames", default="", help="comma-separated frame numbers to keep (e.g. 000001)")
    ap.add_argument("--objects", default="", help="comma-separated object names to keep")
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0],
                    help="multiples of the library's default temperature rule")
    ap.add_argument("--fit", default="", metavar="SCENES",
                    help="fit the rule's scale on these scenes' pairs and sample only the others")
    ap.add_argument("--loso", action="store_true",
                    help="with --calibrated: leave one scene out (fit on the other scenes, score it; "
                         "every pair held out once)")
    ap.add_argument("--calibrated", action="store_true",
                    help="score certpose.sampling.calibration's distribution (basins, model error) "
                         "instead of the sampler at a temperature")
    ap.add_argument("--draws", type=int, default=3000)
    ap.add_argument("--appearance", action="store_true",
                    help="also appearance models from the other scene's views")
    ap.add_argument("--min-px", type=int, default=2000)
    ap.add_argument("--cache", type=Path, default=None, help="directory caching each pair's MLE")
    ap.add_argument("--out", type=Path, default=None, help="append one JSON line per pair")
    ap.add_argument("--summarise", type=Path, default=None, metavar="JSONL",
                    help="only print the summary of the rows of an earlier --out file")
    args = ap.parse_args(argv)
    if args.summarise is not None:
        rows = [json.loads(line) for line in args.summarise.read_text().splitlines() if line.strip()]
        names = sorted({n for r in rows for n in r["levels"]})
        summarise(rows, names)
        return
    if not args.data.is_dir():
        raise SystemExit(f"YCB-Video folder not found: {args.data}")
    if args.cache is not None:
        args.cache.mkdir(parents=True, exist_ok=True)
    from certpose.estimation.pipeline import build_ycbv_object_model
    from certpose.io.ycbv import load_ycbv_frame
    from certpose.sampling.sampler import ISParams

    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}; {args.draws} draws")
    keep = set(filter(None, args.frames.split(",")))
    keep_obj = set(filter(None, args.objects.split(",")))
    fit_scenes = set(filter(None, args.fit.split(",")))
    jobs = []
    models: dict = {}
    for scene in args.scenes.split(","):
        for frame in _frames(args.data, scene):
            if keep and frame.split("/")[1] not in keep:
                continue
            yf = load_ycbv_frame(args.data, frame)
            for obj in sorted(yf.poses):
                if keep_obj and obj not in keep_obj:
                    continue
                try:
                    if yf.object_mask(obj).sum() <= args.min_px:
                        continue
                except (KeyError, ValueError):
                    continue
                jobs.append((frame, obj, None))
                other = OTHER_SCENE.get((obj, scene))
                if args.appearance and other is not None:
                    if (obj, other) not in models:
                        models[(obj, other)] = build_ycbv_object_model(
                            args.data, _frames(args.data, other), obj)
                    jobs.append((frame, obj, models[(obj, other)]))
    if args.cache is None:
        import tempfile

        args.cache = Path(tempfile.mkdtemp(prefix="calib-cache-"))
    # First pass: the MLE side of every pair (cached); the likelihoods are rebuilt when sampled.
    infos = [prepare_pair(args.data, frame, obj, om, args.cache, likelihood=False)[1]
             for frame, obj, om in jobs]
    default_scale = ISParams().temperature_scale
    if args.calibrated:
        run_calibrated(args, jobs, infos, fit_scenes)
        return
    if fit_scenes:
        train = [i for i in infos if i["scene"] in fit_scenes]
        if not train:
            raise SystemExit(f"--fit {args.fit}: no pairs in those scenes")
        scale = {"fit": fit_scale(train)}
        for kind in ("geometry", "appearance"):
            sub = [i for i in train if i["model"] == kind]
            if sub:
                scale[kind] = fit_scale(sub)
        print(f"fitted on {len(train)} pairs of {sorted(fit_scenes)}: scale of N / n_eff "
              + ", ".join(f"{k} {v:.2f}" for k, v in scale.items())
              + f" (library default {default_scale:g})")
        jobs = [j for j, i in zip(jobs, infos, strict=True) if i["scene"] not in fit_scenes]
        temps = lambda i: {"fit": scale["fit"] * i["T0"]}  # noqa: E731
    else:
        temps = lambda i: {f"x{s:g}": s * default_scale * i["T0"] for s in args.scales}  # noqa: E731
    rows = []
    for frame, obj, om in jobs:
        lik, info = prepare_pair(args.data, frame, obj, om, args.cache)
        row = sample_pair(lik, info, temps(info), args.draws)
        rows.append(row)
        print(json.dumps(row), flush=True)
        if args.out is not None:
            with open(args.out, "a") as fh:
                fh.write(json.dumps(row) + "\n")
    if rows:
        summarise(rows, list(rows[0]["levels"]),
                  f"held out (fit on {args.fit})" if fit_scenes else "")


if __name__ == "__main__":
    main()
