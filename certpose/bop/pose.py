"""Pose the targets of one BOP image: what one task of a dataset run does.

Each target instance is posed as :func:`certpose.estimation.pipeline.run_ycbv` poses a
YCB-Video object with its mask: the scene field built from the image cropped to the instance's
visible mask (``mask_visib``) grown by ``PoseParams.roi_margin``, the geometry-only FPFH model
of the dataset's model points (built once per process and kept in the model cache, see
:func:`object_model`), the mask classifier, and :func:`~certpose.estimation.pipeline.estimate_pose`
seeded with ``seed`` for every instance. The image is read once for all its targets. Tasks
receive paths and ids, never arrays: a Dask worker reads what it poses.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["object_model", "pose_image"]

log = logging.getLogger(__name__)

_MODELS: dict[tuple[Any, ...], Any] = {}


def object_model(ds: Any, obj_id: int, params: Any, *, cache_dir: str | Path | None = None) -> Any:
    """The geometry-only object model of ``obj_id`` (FPFH descriptors, the pipeline's voxel size
    and revolution option), built once per process and dataset object; with ``cache_dir``
    kept on disk across processes (:func:`~certpose.io.cache.object_from_points_cached`), and
    so is its visibility table when eq. (1) weighs points by visibility
    (:func:`~certpose.io.cache.visibility_table_cached`): a dataset run's workers read both
    instead of building them each."""
    from certpose.geometry.features import FPFHBackbone
    from certpose.io.cache import object_from_points_cached, visibility_table_cached

    key = (str(ds.root.resolve()), int(obj_id), float(params.voxel_size),
           bool(params.model_revolution), None if cache_dir is None else str(cache_dir))
    if key not in _MODELS:
        obj = ds.object(obj_id)
        model = object_from_points_cached(
            obj.points, FPFHBackbone(), voxel_size=params.voxel_size, name=obj.name,
            cache_dir=cache_dir, revolution="auto" if params.model_revolution else None)
        lik = params.likelihood
        if (cache_dir is not None and lik.visibility and lik.free_space != "voxels"
                and model.normals is not None):
            visibility_table_cached(model.points, model.normals, grazing=lik.visibility_grazing,
                                    cache_dir=cache_dir)
        _MODELS[key] = model
    return _MODELS[key]


def _gap_cells(result: Any) -> dict[str, Any]:
    c = result.certificate
    if c is None:
        return {"certified": None, "relative_gap": None, "lower_bound": None, "upper_bound": None}
    return {"certified": bool(c.certified), "relative_gap": float(c.relative_gap),
            "lower_bound": float(c.lower_bound), "upper_bound": float(c.upper_bound)}


def _pose_instance(ds: Any, frame: Any, scene_id: int, im_id: int, inst: Any, params: Any,
                   seed: int, cache_dir: Any, particles_dir: Path | None) -> tuple[dict, Any]:
    from certpose.estimation.pipeline import _scene_for, estimate_pose
    from certpose.geometry.features import FPFHBackbone

    t0 = time.perf_counter()
    mask = ds.mask_visib(scene_id, im_id, inst.gt_id, frame.depth.shape)
    if not mask.any():
        raise ValueError(f"the visible mask of instance {inst.gt_id} is empty")
    scene = _scene_for(frame, mask, params, FPFHBackbone())
    model = object_model(ds, inst.obj_id, params, cache_dir=cache_dir)
    points = ds.object(inst.obj_id).points
    result = estimate_pose(scene, model, classifier="mask", frame=frame.with_mask(mask),
                           params=params, rng=seed, T_camera_object_gt=inst.T_camera_object,
                           gt_model_points=points)
    e = result.errors
    side = {"gt_id": inst.gt_id, "success": bool(result.success), "status": result.status,
            "score": float(result.log_likelihood), "log_likelihood": float(result.log_likelihood),
            **_gap_cells(result), "modes": len(result.modes),
            "ess": result.sampling.get("ess") if result.sampling else None,
            "pareto_k": result.sampling.get("pareto_k") if result.sampling else None,
            "add_s_mm": None if e is None else 1000.0 * e.add_s,
            "add_mm": None if e is None else 1000.0 * e.add,
            "rotation_error_deg": None if e is None else e.rotation_deg,
            "seconds": time.perf_counter() - t0, "particles": None, "error": None}
    if particles_dir is not None and result.distribution is not None:
        path = particles_dir / f"{scene_id:06d}_{im_id:06d}_{inst.obj_id:06d}_{inst.gt_id:06d}.npz"
        result.distribution.save(path)
        side["particles"] = path.name
    return side, result


def pose_image(root: str, split: str, scene_id: int, im_id: int,
               targets: Sequence[tuple[int, int]], *, params: Any = None, seed: int = 0,
               cache_dir: str | None = None, particles_dir: str | None = None
               ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Pose the targets of one image.

    Parameters
    ----------
    root, split : str
        The BOP dataset folder and split.
    scene_id, im_id : int
    targets : sequence of (obj_id, inst_count)
        The image's targets; for each, the ``inst_count`` most visible instances of the object
        are posed (as the BOP evaluation counts them).
    params : PoseParams, optional
    seed : int
        The seed of every instance's estimate (each one as ``certpose pose --seed``).
    cache_dir : str, optional
        The object-model cache.
    particles_dir : str, optional
        With ``params.sampler``: each instance's particles are saved there as
        ``{scene}_{im}_{obj}_{gt}.npz`` (``T_camera_object``).

    Returns
    -------
    bop_rows : list of dict
        :data:`~certpose.bop.results.BOP_COLUMNS` rows of the instances posed successfully.
    side_rows : list of dict
        :data:`~certpose.bop.results.SIDE_COLUMNS` rows, one per instance (failures with their
        ``error``).
    """
    from certpose.bop.results import bop_row_cells
    from certpose.estimation.pipeline import PoseParams
    from certpose.io.bop import open_dataset

    params = params or PoseParams()
    t0 = time.perf_counter()
    ds = open_dataset(str(root), str(split))
    frame = ds.frame(scene_id, im_id)
    instances = ds.instances(scene_id, im_id)
    pdir = None if particles_dir is None else Path(particles_dir)
    side_rows, poses = [], []
    for obj_id, count in targets:
        mine = sorted((i for i in instances if i.obj_id == obj_id),
                      key=lambda i: -(i.visib_fract if i.visib_fract is not None else 1.0))
        for k in range(count):
            base = {"scene_id": scene_id, "im_id": im_id, "obj_id": obj_id}
            if k >= len(mine):
                side_rows.append({**base, "gt_id": None, "success": False, "status": "error",
                                  "error": f"the image has {len(mine)} instance(s) of object "
                                           f"{obj_id}, the target {count}"})
                continue
            try:
                side, result = _pose_instance(ds, frame, scene_id, im_id, mine[k], params, seed,
                                              cache_dir, pdir)
            except (ValueError, KeyError, OSError, RuntimeError) as exc:
                log.warning("scene %d image %d object %d: %s", scene_id, im_id, obj_id, exc)
                side_rows.append({**base, "gt_id": mine[k].gt_id, "success": False,
                                  "status": "error", "error": f"{type(exc).__name__}: {exc}"})
                continue
            side_rows.append({**base, **side})
            if result.success and np.isfinite(result.T_camera_object).all():
                poses.append((base, side["score"], result.T_camera_object))
    seconds = time.perf_counter() - t0
    bop_rows = []
    for base, score, T in poses:
        R, t = bop_row_cells(T)
        bop_rows.append({**base, "score": score if math.isfinite(score) else -1e30, "R": R,
                         "t": t, "time": seconds})
    return bop_rows, side_rows
