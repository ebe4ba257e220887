"""BOP 2019 scores of a results file: VSD, MSSD and MSPD recalls, their average recalls (AR),
and ADD(-S) and rotation errors beside them.

The protocol is the BOP toolkit's (``scripts/eval_bop19_pose.py`` with its defaults): for each
target ``(scene, image, object, inst_count)`` the ``inst_count`` estimates with the highest
score are compared with every ground-truth instance of the object; the ``inst_count`` most
visible instances are the valid ones. For each metric and threshold, estimates are matched
greedily in order of decreasing score to the valid, still unmatched instance with the smallest
error below the threshold; the recall is the matched instances over the valid ones. VSD uses
``delta`` = 15 mm and ``tau`` = 0.05, 0.10, ..., 0.50 of the diameter, each with the
thresholds 0.05, ..., 0.50; MSSD the thresholds 0.05, ..., 0.50 of the diameter; MSPD 5, ..., 50
pixels times 640 / image width. AR per metric is the mean of its recalls, AR their mean.
Continuous symmetries are discretised with the toolkit's step (0.01).
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["BOPScores", "VSD_TAUS", "VSD_THRESHOLDS", "MSSD_THRESHOLDS", "MSPD_THRESHOLDS",
           "score_bop", "estimate_errors", "match_and_recall"]

log = logging.getLogger(__name__)

VSD_DELTA = 0.015
VSD_TAUS = tuple(np.arange(0.05, 0.51, 0.05))
VSD_THRESHOLDS = tuple(np.arange(0.05, 0.51, 0.05))
MSSD_THRESHOLDS = tuple(np.arange(0.05, 0.51, 0.05))
MSPD_THRESHOLDS = tuple(np.arange(5, 51, 5).astype(float))


@dataclass(frozen=True)
class BOPScores:
    """Scores of a results file.

    Attributes
    ----------
    ar : dict of str to float
        ``"vsd"``, ``"mssd"``, ``"mspd"`` (average recalls) and ``"ar"`` (their mean).
    recalls : dict of str to list of float
        Per metric, its recalls in the order of its (tau, threshold) settings.
    targets : int
        Valid ground-truth instances.
    estimates : int
        Estimates evaluated (at most ``inst_count`` per target).
    per_target : list of dict
        Per valid instance: ids, whether it had an estimate, its errors (``vsd`` at tau = 0.2,
        ``mssd``/``add``/``add_s``/``translation`` in metres, ``mspd`` in pixels,
        ``rotation_deg``).
    add_s : dict
        ``"recall_0.1d"``: the share of instances with ADD(-S) below 0.1 of the diameter
        (ADD-S for objects with symmetries in ``models_info.json``, ADD otherwise);
        ``"mean_m"``: mean ADD(-S) of the instances with an estimate.
    rotation_error_deg : dict
        Median and mean geodesic rotation error of the instances with an estimate.
    """

    ar: dict[str, float]
    recalls: dict[str, list[float]]
    targets: int
    estimates: int
    per_target: list[dict[str, Any]] = field(repr=False)
    add_s: dict[str, float]
    rotation_error_deg: dict[str, float]
    success: bool = True
    status: str = "ok"
    message: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def _renderer(cache: dict[int, Any], obj: Any) -> Any:
    from certpose.bop.render import MeshDepthRenderer

    if obj.obj_id not in cache:
        if obj.faces is None:
            raise ValueError(f"Object {obj.obj_id}'s model has no faces: VSD renders a mesh.")
        cache[obj.obj_id] = MeshDepthRenderer(obj.points, obj.faces)
    return cache[obj.obj_id]


def estimate_errors(est: dict[str, Any], gt: Any, obj: Any, K: np.ndarray,
                    depth_test: np.ndarray, renderer: Any) -> dict[str, Any]:
    """Every error of one estimate against one ground-truth instance (metres, pixels)."""
    from certpose.bop.metrics import (
        add,
        adi,
        mspd,
        mssd,
        sphere_projections_overlap,
        spheres_overlap,
        vsd,
    )
    from solvers.lie import rotation_error_deg

    R_e, t_e = est["R"], est["t"]
    R_g, t_g = gt.T_camera_object[:3, :3], gt.T_camera_object[:3, 3]
    d = obj.diameter
    if sphere_projections_overlap(t_e, t_g, 0.5 * d):
        T_e = np.eye(4)
        T_e[:3, :3], T_e[:3, 3] = R_e, t_e
        shape = depth_test.shape
        e_vsd = vsd(renderer.depth(T_e, K, shape), renderer.depth(gt.T_camera_object, K, shape),
                    depth_test, K, delta=VSD_DELTA, taus=VSD_TAUS, diameter=d)
    else:
        e_vsd = np.ones(len(VSD_TAUS))
    near = spheres_overlap(t_e, t_g, d)
    e_add = add(R_e, t_e, R_g, t_g, obj.points)
    e_adi = adi(R_e, t_e, R_g, t_g, obj.points)
    return {"vsd": [float(v) for v in e_vsd],
            "mssd": mssd(R_e, t_e, R_g, t_g, obj.points, obj.symmetries) if near else math.inf,
            "mspd": mspd(R_e, t_e, R_g, t_g, K, obj.points, obj.symmetries),
            "add": e_add, "add_s": e_adi,
            "rotation_deg": rotation_error_deg(R_e, R_g),
            "translation": float(np.linalg.norm(np.reshape(t_e, 3) - np.reshape(t_g, 3)))}


def match_and_recall(items: list[dict[str, Any]], valid_count: int, error: Any,
                     threshold: float) -> float:
    """The recall at one threshold: ``items`` are the estimates of the run, each ``{"key":
    (scene, image, object), "score", "errors": {gt key: error value}}``; matching is greedy by
    decreasing score within each (scene, image, object), each valid instance matched once."""
    tps = 0
    groups: dict[Any, list[dict[str, Any]]] = {}
    for it in items:
        groups.setdefault(it["key"], []).append(it)
    for ests in groups.values():
        matched: set[Any] = set()
        for e in sorted(ests, key=lambda x: x["score"], reverse=True):
            best, best_err = None, threshold
            for gt_key, errs in e["errors"].items():
                v = error(errs)
                if gt_key not in matched and v < best_err:
                    best, best_err = gt_key, v
            if best is not None:
                matched.add(best)
                tps += 1
    return 0.0 if valid_count == 0 else tps / float(valid_count)


def score_bop(root: str | os.PathLike[str], results: str | os.PathLike[str], *,
              split: str = "test", targets: str | os.PathLike[str] | None = None) -> BOPScores:
    """Score a BOP results file on a dataset (see the module docstring).

    Parameters
    ----------
    root : path
        The BOP dataset folder.
    results : path
        ``scene_id,im_id,obj_id,score,R,t,time`` CSV.
    split : str
    targets : path, optional
        Default ``<root>/test_targets_bop19.json``.

    Raises
    ------
    ValueError
        A results row for an image that has no target is ignored; a malformed file raises.
    """
    from certpose.bop.results import read_bop_results
    from certpose.io.bop import BOPDataset, group_targets

    ds = BOPDataset(root, split)
    tgts = group_targets(ds.targets(targets))
    ests: dict[tuple[int, int, int], list[dict[str, Any]]] = {}
    for r in read_bop_results(results):
        ests.setdefault((r["scene_id"], r["im_id"], r["obj_id"]), []).append(r)
    renderers: dict[int, Any] = {}
    items: list[dict[str, Any]] = []
    per_target: list[dict[str, Any]] = []
    widths: dict[tuple[int, int], int] = {}
    valid_count = 0
    for (scene_id, im_id), im_targets in sorted(tgts.items()):
        K, _ = ds.camera(scene_id, im_id)
        depth = ds.frame(scene_id, im_id, color=False).depth
        widths[(scene_id, im_id)] = depth.shape[1]
        insts = ds.instances(scene_id, im_id)
        for t in im_targets:
            obj = ds.object(t.obj_id)
            mine = sorted((i for i in insts if i.obj_id == t.obj_id),
                          key=lambda i: -(i.visib_fract if i.visib_fract is not None else 1.0))
            valid = mine[:t.inst_count]
            valid_count += len(valid)
            key = (scene_id, im_id, t.obj_id)
            top = sorted(ests.get(key, []), key=lambda e: e["score"], reverse=True)[:t.inst_count]
            for e in top:
                errs = {(key, g.gt_id): estimate_errors(e, g, obj, K, depth,
                                                        _renderer(renderers, obj))
                        for g in valid}
                items.append({"key": key, "score": e["score"], "errors": errs,
                              "diameter": obj.diameter, "width": depth.shape[1]})
            for k, g in enumerate(valid):
                row: dict[str, Any] = {"scene_id": scene_id, "im_id": im_id,
                                       "obj_id": t.obj_id, "gt_id": g.gt_id,
                                       "estimated": k < len(top)}
                if k < len(top):
                    e = items[len(items) - len(top) + k]["errors"][(key, g.gt_id)]
                    row.update({"vsd_tau0.2": e["vsd"][3], "mssd": e["mssd"], "mspd": e["mspd"],
                                "add": e["add"], "add_s": e["add_s"],
                                "rotation_deg": e["rotation_deg"],
                                "translation": e["translation"],
                                "symmetric": len(obj.symmetries) > 1,
                                "diameter": obj.diameter})
                per_target.append(row)
    return _summarise(items, valid_count, per_target)


def _summarise(items: list[dict[str, Any]], valid_count: int,
               per_target: list[dict[str, Any]]) -> BOPScores:
    recalls: dict[str, list[float]] = {"vsd": [], "mssd": [], "mspd": []}
    # Normalised as the toolkit's eval_calc_scores: MSSD by the diameter, MSPD by 640 / width.
    for k in range(len(VSD_TAUS)):
        for th in VSD_THRESHOLDS:
            recalls["vsd"].append(match_and_recall(items, valid_count,
                                                   lambda e, k=k: e["vsd"][k], th))
    for th in MSSD_THRESHOLDS:
        recalls["mssd"].append(match_and_recall(
            [dict(it, errors={g: {"v": e["mssd"] / it["diameter"]}
                              for g, e in it["errors"].items()}) for it in items],
            valid_count, lambda e: e["v"], th))
    for th in MSPD_THRESHOLDS:
        recalls["mspd"].append(match_and_recall(
            [dict(it, errors={g: {"v": e["mspd"] * 640.0 / it["width"]}
                              for g, e in it["errors"].items()}) for it in items],
            valid_count, lambda e: e["v"], th))
    ar = {m: float(np.mean(v)) for m, v in recalls.items()}
    ar["ar"] = float(np.mean([ar["vsd"], ar["mssd"], ar["mspd"]]))
    done = [r for r in per_target if r["estimated"]]
    add_s = [r["add_s"] if r["symmetric"] else r["add"] for r in done]
    hits = sum(v < 0.1 * r["diameter"] for v, r in zip(add_s, done, strict=True))
    rot = [r["rotation_deg"] for r in done]
    n_est = len(items)
    return BOPScores(
        ar, recalls, valid_count, n_est, per_target,
        {"recall_0.1d": 0.0 if valid_count == 0 else hits / valid_count,
         "mean_m": float(np.mean(add_s)) if add_s else math.nan},
        {"median": float(np.median(rot)) if rot else math.nan,
         "mean": float(np.mean(rot)) if rot else math.nan},
        True, "ok",
        f"{n_est} estimate(s) for {valid_count} target instance(s): AR {ar['ar']:.3f} "
        f"(VSD {ar['vsd']:.3f}, MSSD {ar['mssd']:.3f}, MSPD {ar['mspd']:.3f})")


def write_errors(path: str | os.PathLike[str], scores: BOPScores) -> Path:
    """The per-instance errors of ``scores`` as CSV."""
    import csv

    cols = ["scene_id", "im_id", "obj_id", "gt_id", "estimated", "vsd_tau0.2", "mssd", "mspd",
            "add", "add_s", "rotation_deg", "translation", "symmetric", "diameter"]
    p = Path(path)
    with p.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, lineterminator="\n", restval="")
        w.writeheader()
        w.writerows(scores.per_target)
    return p
