"""Compare `certpose score --bop` with the BOP toolkit's own functions on the same inputs.

The toolkit (github.com/thodan/bop_toolkit, not a dependency) reads the dataset and the results
file with its own readers (millimetres), computes VSD / MSSD / MSPD with ``pose_error``, matches
with ``pose_matching.match_poses_scene`` and scores with ``score.calc_localization_scores``, as
``scripts/eval_calc_errors.py`` and ``scripts/eval_calc_scores.py`` do with BOP 2019's settings
(``visib_gt_min = -1``, ``n_top = -1``, ``max_sym_disc_step = 0.01``). Its renderers need OpenGL;
VSD's depth renderings come from certpose's ray caster here (in millimetres) through the
toolkit's renderer interface, so the check covers everything but the rasterisation.

Run with the toolkit on the path, e.g. in a scratch virtual environment::

    PYTHONPATH=/path/to/bop_toolkit:. python examples/benchmarks/bop_toolkit_check.py \
        /tmp/ycbv_bop results.csv

It prints both sets of average recalls and their largest difference; exit code 1 when it is
above 1e-3.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import defaultdict

import numpy as np


class _Renderer:
    """The toolkit's renderer interface over certpose's ray caster (millimetres)."""

    def __init__(self, models: dict, shape: tuple[int, int]) -> None:
        from certpose.bop.render import MeshDepthRenderer

        self.shape = shape
        self.r = {k: MeshDepthRenderer(m["pts"], m["faces"]) for k, m in models.items()}

    def render_object(self, obj_id, R, t, fx, fy, cx, cy):  # noqa: ANN001, ANN201
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, np.ravel(t)
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        return {"depth": self.r[obj_id].depth(T, K, self.shape)}


def toolkit_scores(ds_path: str, results: str, targets_name: str = "test_targets_bop19.json"
                   ) -> dict[str, float]:
    from bop_toolkit_lib import inout, misc, pose_error, pose_matching, score

    models_info = inout.load_json(os.path.join(ds_path, "models", "models_info.json"),
                                  keys_to_int=True)
    obj_ids = sorted(models_info)
    models = {i: inout.load_ply(os.path.join(ds_path, "models", f"obj_{i:06d}.ply"))
              for i in obj_ids}
    syms = {i: misc.get_symmetry_transformations(models_info[i], 0.01) for i in obj_ids}
    targets = inout.load_json(os.path.join(ds_path, targets_name))
    t_org: dict = {}
    for t in targets:
        t_org.setdefault(t["scene_id"], {}).setdefault(t["im_id"], {})[t["obj_id"]] = t
    ests = inout.load_bop_results(results, version="bop19")
    e_org: dict = {}
    for e in ests:
        e_org.setdefault(e["scene_id"], {}).setdefault(e["im_id"], {}).setdefault(
            e["obj_id"], []).append(e)
    taus = list(np.arange(0.05, 0.51, 0.05))
    errs = defaultdict(list)  # (type, tau index or None) -> scene errors list with scene id
    scene_data = {}
    renderer = None
    for scene_id, s_targets in t_org.items():
        sdir = os.path.join(ds_path, "test", f"{scene_id:06d}")
        scene_gt = inout.load_scene_gt(os.path.join(sdir, "scene_gt.json"))
        scene_gt_info = inout.load_json(os.path.join(sdir, "scene_gt_info.json"),
                                        keys_to_int=True)
        scene_cam = inout.load_scene_camera(os.path.join(sdir, "scene_camera.json"))
        scene_data[scene_id] = (scene_gt, scene_gt_info)
        for im_id, im_targets in s_targets.items():
            K = scene_cam[im_id]["cam_K"]
            depth = inout.load_depth(os.path.join(sdir, "depth", f"{im_id:06d}.png"))
            depth *= scene_cam[im_id]["depth_scale"]
            if renderer is None:
                renderer = _Renderer(models, depth.shape)
            for obj_id, target in im_targets.items():
                obj_ests = e_org.get(scene_id, {}).get(im_id, {}).get(obj_id, [])
                srt = sorted(enumerate(obj_ests), key=lambda x: x[1]["score"], reverse=True)
                for est_id, est in srt[:target["inst_count"]]:
                    per = defaultdict(dict)
                    vis = {}
                    for gt_id, gt in enumerate(scene_gt[im_id]):
                        if gt["obj_id"] != obj_id:
                            continue
                        R_g, t_g = gt["cam_R_m2c"], gt["cam_t_m2c"]
                        R_e, t_e = est["R"], est["t"]
                        vis[gt_id] = scene_gt_info[im_id][gt_id]["visib_fract"]
                        diam = models_info[obj_id]["diameter"]
                        if misc.overlapping_sphere_projections(0.5 * diam, t_e.squeeze(),
                                                               t_g.squeeze()):
                            e = pose_error.vsd(R_e, t_e, R_g, t_g, depth, K, 15, taus, True,
                                               diam, renderer, obj_id, "step")
                        else:
                            e = [1.0] * len(taus)
                        for k, v in enumerate(e):
                            per[("vsd", k)][gt_id] = [v]
                        if np.linalg.norm(t_e - t_g) < diam:
                            per[("mssd", None)][gt_id] = [pose_error.mssd(
                                R_e, t_e, R_g, t_g, models[obj_id]["pts"], syms[obj_id])]
                        else:
                            per[("mssd", None)][gt_id] = [float("inf")]
                        per[("mspd", None)][gt_id] = [pose_error.mspd(
                            R_e, t_e, R_g, t_g, K, models[obj_id]["pts"], syms[obj_id])]
                    for key, e_map in per.items():
                        errs[key].append((scene_id, {"im_id": im_id, "obj_id": obj_id,
                                                     "est_id": est_id, "score": est["score"],
                                                     "errors": e_map,
                                                     "gt_visib_fracts": vis,
                                                     "width": depth.shape[1]}))
    settings = ([(("vsd", k), th) for k in range(len(taus)) for th in np.arange(0.05, 0.51, 0.05)]
                + [(("mssd", None), th) for th in np.arange(0.05, 0.51, 0.05)]
                + [(("mspd", None), th) for th in np.arange(5, 51, 5)])
    recalls = defaultdict(list)
    for key, th in settings:
        matches = []
        for scene_id, s_targets in t_org.items():
            scene_gt, scene_gt_info = scene_data[scene_id]
            gt_curr, info_curr, valid = {}, {}, {}
            for im_id, im_targets in s_targets.items():
                im_gt = scene_gt[im_id]
                gt_curr[im_id], info_curr[im_id] = im_gt, scene_gt_info[im_id]
                valid[im_id] = [False] * len(im_gt)
                order = sorted(range(len(im_gt)),
                               key=lambda g, im_id=im_id: scene_gt_info[im_id][g]["visib_fract"],
                               reverse=True)
                to_add = {o: t["inst_count"] for o, t in im_targets.items()}
                for g in order:
                    o = im_gt[g]["obj_id"]
                    if to_add.get(o, 0) > 0:
                        valid[im_id][g] = True
                        to_add[o] -= 1
            s_errs = []
            for sid, e in errs[key]:
                if sid != scene_id:
                    continue
                e = dict(e, errors={g: list(v) for g, v in e["errors"].items()})
                if key[0] == "mssd":
                    d = float(models_info[e["obj_id"]]["diameter"])
                    e["errors"] = {g: [v[0] / d] for g, v in e["errors"].items()}
                if key[0] == "mspd":
                    f = 640.0 / e["width"]
                    e["errors"] = {g: [v[0] * f] for g, v in e["errors"].items()}
                s_errs.append(e)
            matches += pose_matching.match_poses_scene(scene_id, gt_curr, info_curr, valid,
                                                       s_errs, [th], -1)
        sc = score.calc_localization_scores(list(t_org), obj_ids, matches, -1, do_print=False)
        recalls[key[0]].append(sc["recall"])
    ar = {m: float(np.mean(v)) for m, v in recalls.items()}
    ar["ar"] = float(np.mean([ar["vsd"], ar["mssd"], ar["mspd"]]))
    return ar


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("bop", help="the BOP dataset folder")
    p.add_argument("results", help="the BOP results CSV")
    args = p.parse_args()
    from certpose.bop.score import score_bop

    ours = score_bop(args.bop, args.results).ar
    theirs = toolkit_scores(args.bop, args.results)
    diff = max(abs(ours[k] - theirs[k]) for k in ("vsd", "mssd", "mspd", "ar"))
    for k in ("vsd", "mssd", "mspd", "ar"):
        print(f"AR_{k}: certpose {ours[k]:.6f}  BOP toolkit {theirs[k]:.6f}")
    print(f"largest difference: {diff:.2e}")
    return 0 if diff <= 1e-3 else 1


if __name__ == "__main__":
    sys.exit(main())
