"""Write YCB-Video frames (and the synthetic demo scene) as a BOP-layout dataset folder.

The shared YCB-Video frames become ``test/<scene>/`` folders (scene and image ids are the
frames' folder and file numbers, object ids the YCB-Video class indices, as in BOP's YCB-V):
the colour and depth images are copied unchanged (``depth_scale`` = 1000 / ``factor_depth``,
0.1 mm for YCB-Video, as BOP's YCB-V), ``mask_visib`` is the label image of each object, and
the poses are the frames' ground truth in millimetres. The models are the shared model points
(2621 per object), written in millimetres as the vertices of a ball-pivoting mesh over them
(the vertices are the points themselves, in order, so that a pose run on the converted folder
sees the same points as one on the frames; the mesh has holes where the points are sparse).
``models_info.json`` gives the diameter (largest distance between two vertices), the
bounding box and, for the objects BOP's YCB-V declares symmetric, the symmetries found on these
points in their frame (:func:`find_symmetries`). ``scene_gt_info.json`` counts the mask's
pixels against the mesh's silhouette rendered at the ground truth, and
``test_targets_bop19.json`` lists every instance at least ``min_visib_fract`` visible.
"""

from __future__ import annotations

import logging
import math
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from certpose.io.bop import MM, write_bop_json, write_bop_ply

__all__ = ["YCBV_SYMMETRIC_OBJ_IDS", "convert_ycbv", "convert_demo", "ball_pivoting_mesh",
           "find_symmetries", "model_info"]

log = logging.getLogger(__name__)

#: Objects of BOP's YCB-V with symmetries (the BOP toolkit's ``symmetric_obj_ids``):
#: master chef can, bowl, mug, wood block, large marker, large and extra large clamps, foam
#: brick (YCB-Video class indices).
YCBV_SYMMETRIC_OBJ_IDS = (1, 13, 14, 16, 18, 19, 20, 21)


def ball_pivoting_mesh(points: NDArray[np.float64]) -> NDArray[np.int64]:
    """Triangles (M, 3) over ``points`` (open3d's ball pivoting at 1.5, 3, 6 and 12 times the
    median nearest-neighbour spacing; normals oriented consistently and outwards). The
    vertices are ``points`` themselves."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    spacing = float(np.median(cKDTree(points).query(points, k=2)[0][:, 1]))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * spacing, max_nn=30))
    pcd.orient_normals_consistent_tangent_plane(10)
    n = np.asarray(pcd.normals)
    if np.sum(n * (points - points.mean(axis=0))) < 0:
        pcd.normals = o3d.utility.Vector3dVector(-n)
    radii = o3d.utility.DoubleVector([f * spacing for f in (1.5, 3.0, 6.0, 12.0)])
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(pcd, radii)
    if len(mesh.vertices) != len(points):  # ball pivoting keeps the input points as vertices
        raise RuntimeError("ball pivoting changed the vertices")
    return np.asarray(mesh.triangles, dtype=np.int64)


def _diameter(points: NDArray[np.float64]) -> float:
    from scipy.spatial import ConvexHull
    from scipy.spatial.distance import pdist

    hull = points[ConvexHull(points).vertices]
    return float(pdist(hull).max())


def _symmetry_residual(points: NDArray[np.float64], tree: Any, S: NDArray[np.float64]) -> float:
    moved = points @ S[:3, :3].T + S[:3, 3]
    return float(np.quantile(tree.query(moved)[0], 0.9))


def _axis_candidates(points: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """The coordinate axes (models are usually aligned with their box), then the principal
    axes of the points that are more than 5 degrees from them."""
    c = points - points.mean(axis=0)
    _, vecs = np.linalg.eigh(c.T @ c)
    out = [a for a in np.eye(3)]
    for a in vecs.T:
        if all(abs(a @ b) < math.cos(math.radians(5.0)) for b in out):
            out.append(a / np.linalg.norm(a))
    return out


def find_symmetries(points: NDArray[np.float64], *, tolerance: float | None = None
                    ) -> tuple[list[NDArray[np.float64]], list[dict[str, Any]]]:
    """Symmetries of a model's points in its own frame, in ``models_info.json``'s terms.

    Candidates: a continuous rotation about each coordinate or principal axis through the
    centre of the bounding box (accepted when turns of 30, 60, ..., 330 deg all map the points onto
    themselves), else the half turns about the principal axes and the quarter turns about an
    axis with a square cross-section. A transformation is accepted when 90% of the moved points
    lie within ``tolerance`` of a model point (default: three times the 90th percentile of the
    points' own nearest-neighbour spacing: the shared models are noisy scans).

    Parameters
    ----------
    points : (N, 3) ndarray
        Metres.

    Returns
    -------
    discrete : list of (4, 4) ndarray
        Translations in metres.
    continuous : list of dict
        ``{"axis": (3,), "offset": (3,) metres}``.
    """
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    tree = cKDTree(points)
    if tolerance is None:
        tolerance = 3.0 * float(np.quantile(tree.query(points, k=2)[0][:, 1], 0.9))
    centre = 0.5 * (points.min(axis=0) + points.max(axis=0))

    def about(axis: NDArray[np.float64], angle: float) -> NDArray[np.float64]:
        S = np.eye(4)
        S[:3, :3] = Rotation.from_rotvec(axis * math.radians(angle)).as_matrix()
        S[:3, 3] = centre - S[:3, :3] @ centre
        return S

    def ok(S: NDArray[np.float64]) -> bool:
        return _symmetry_residual(points, tree, S) <= tolerance

    axes = _axis_candidates(points)
    for a in axes:
        if all(ok(about(a, ang)) for ang in range(30, 360, 30)):
            flips = [about(b, 180.0) for b in axes if abs(b @ a) < 0.5 and ok(about(b, 180.0))]
            return flips[:1], [{"axis": a, "offset": centre}]
    discrete = []
    for a in axes:
        if ok(about(a, 90.0)) and ok(about(a, 270.0)):
            discrete += [about(a, 90.0), about(a, 180.0), about(a, 270.0)]
        elif ok(about(a, 180.0)):
            discrete.append(about(a, 180.0))
    # The composition of two half turns is the third: keep the group closed.
    unique: list[NDArray[np.float64]] = []
    for S in discrete:
        if not any(np.allclose(S, U, atol=1e-9) for U in unique):
            unique.append(S)
    return unique, []


def model_info(points: NDArray[np.float64], *, symmetric: bool) -> dict[str, Any]:
    """A ``models_info.json`` entry (millimetres) for model points in metres."""
    lo, hi = points.min(axis=0) * MM, points.max(axis=0) * MM
    info: dict[str, Any] = {"diameter": _diameter(points) * MM,
                            "min_x": lo[0], "min_y": lo[1], "min_z": lo[2],
                            "size_x": hi[0] - lo[0], "size_y": hi[1] - lo[1],
                            "size_z": hi[2] - lo[2]}
    info = {k: float(v) for k, v in info.items()}
    if symmetric:
        disc, cont = find_symmetries(points)
        if disc:
            mm = []
            for S in disc:
                S = S.copy()
                S[:3, 3] *= MM
                mm.append([float(v) for v in S.ravel()])
            info["symmetries_discrete"] = mm
        if cont:
            info["symmetries_continuous"] = [
                {"axis": [float(v) for v in c["axis"]],
                 "offset": [float(v) * MM for v in c["offset"]]} for c in cont]
    return info


def _bbox(mask: NDArray[np.bool_]) -> list[int]:
    """``[x, y, w, h]`` of a mask's pixels (``[-1, -1, -1, -1]`` when empty), as BOP's."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]


def _write_mask(path: Path, mask: NDArray[np.bool_]) -> None:
    import imageio.v3 as iio

    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, (mask.astype(np.uint8) * 255))


def _frames(root: Path, frames: Sequence[str] | None) -> list[str]:
    if frames is not None:
        return list(frames)
    return sorted(f"{p.parent.name}/{p.name[:-len('-meta.mat')]}"
                  for p in root.glob("*/*-meta.mat") if p.parent.name.isdigit())


def convert_ycbv(root: str | Path, out: str | Path, *, frames: Sequence[str] | None = None,
                 split: str = "test", min_visib_fract: float = 0.1) -> dict[str, Any]:
    """Write YCB-Video frames as a BOP dataset folder (see the module docstring).

    Parameters
    ----------
    root : path
        YCB-Video folder (``<scene>/<frame>-*`` and ``models/``).
    out : path
        The BOP folder to write (created; existing files of the same names are replaced).
    frames : sequence of str, optional
        ``"<scene>/<frame>"`` names (default: every frame under ``root``).
    split : str
    min_visib_fract : float
        Instances at least this visible become targets (BOP 2019: 0.1).

    Returns
    -------
    dict
        ``images``, ``instances``, ``targets``, ``objects`` (ids), ``symmetries`` (per id:
        discrete count and continuous axes).

    Raises
    ------
    FileNotFoundError
        A missing frame or model file.
    ValueError
        No frames.
    """
    from certpose.bop.render import MeshDepthRenderer
    from certpose.io.ycbv import load_class_names, load_model_points, load_ycbv_frame

    root, out = Path(root), Path(out)
    names = _frames(root, frames)
    if not names:
        raise ValueError(f"No YCB-Video frames (<scene>/<frame>-meta.mat) under {root}.")
    classes = load_class_names(root)
    loaded = [load_ycbv_frame(root, n) for n in names]
    obj_ids = sorted({i for yf in loaded for i in yf.class_indexes})
    models: dict[int, tuple[NDArray[np.float64], NDArray[np.int64]]] = {}
    info: dict[str, Any] = {}
    for obj_id in obj_ids:
        pts = load_model_points(root / "models" / classes[obj_id - 1] / "points.xyz")
        faces = ball_pivoting_mesh(pts)
        models[obj_id] = (pts, faces)
        write_bop_ply(out / "models" / f"obj_{obj_id:06d}.ply", pts * MM, faces)
        info[str(obj_id)] = model_info(pts, symmetric=obj_id in YCBV_SYMMETRIC_OBJ_IDS)
    write_bop_json(out / "models" / "models_info.json", info)
    renderers = {i: MeshDepthRenderer(*models[i]) for i in obj_ids}

    by_scene: dict[int, list[tuple[int, Any, str]]] = {}
    for name, yf in zip(names, loaded, strict=True):
        scene, frame = name.split("/")
        by_scene.setdefault(int(scene), []).append((int(frame), yf, name))
    targets, n_inst = [], 0
    for scene_id, items in sorted(by_scene.items()):
        sdir = out / split / f"{scene_id:06d}"
        cams: dict[str, Any] = {}
        gts: dict[str, Any] = {}
        gt_infos: dict[str, Any] = {}
        for im_id, yf, name in sorted(items, key=lambda x: x[0]):
            for kind, suffix in (("rgb", "color.png"), ("depth", "depth.png")):
                (sdir / kind).mkdir(parents=True, exist_ok=True)
                shutil.copyfile(root / f"{name}-{suffix}", sdir / kind / f"{im_id:06d}.png")
            K = yf.intrinsics.K
            factor = _factor_depth(root, name)
            cams[str(im_id)] = {"cam_K": [float(v) for v in K.ravel()],
                                "depth_scale": MM / factor}
            gts[str(im_id)], gt_infos[str(im_id)] = [], []
            shape = yf.label.shape
            for gt_id, (obj_id, obj) in enumerate(zip(yf.class_indexes, yf.class_names,
                                                      strict=True)):
                T = yf.poses[obj]
                gts[str(im_id)].append({"cam_R_m2c": [float(v) for v in T[:3, :3].ravel()],
                                        "cam_t_m2c": [float(v) * MM for v in T[:3, 3]],
                                        "obj_id": int(obj_id)})
                mask = yf.label == obj_id
                _write_mask(sdir / "mask_visib" / f"{im_id:06d}_{gt_id:06d}.png", mask)
                sil = renderers[obj_id].depth(T, K, shape) > 0
                n_all, n_visib = int(sil.sum()), int(mask.sum())
                fract = 0.0 if n_all == 0 else min(1.0, n_visib / n_all)
                gt_infos[str(im_id)].append({
                    "bbox_obj": _bbox(sil), "bbox_visib": _bbox(mask), "px_count_all": n_all,
                    "px_count_valid": int((sil & (yf.frame.depth > 0)).sum()),
                    "px_count_visib": n_visib, "visib_fract": fract})
                n_inst += 1
                if n_visib > 0 and fract >= min_visib_fract:
                    targets.append({"im_id": im_id, "inst_count": 1, "obj_id": int(obj_id),
                                    "scene_id": scene_id})
        write_bop_json(sdir / "scene_camera.json", cams)
        write_bop_json(sdir / "scene_gt.json", gts)
        write_bop_json(sdir / "scene_gt_info.json", gt_infos)
    write_bop_json(out / f"{split}_targets_bop19.json", targets)
    log.info("wrote %d images, %d instances, %d targets to %s", len(names), n_inst,
             len(targets), out)
    return {"images": len(names), "instances": n_inst, "targets": len(targets),
            "objects": obj_ids, "out": str(out),
            "symmetries": {int(k): {"discrete": len(v.get("symmetries_discrete", [])),
                                    "continuous": [c["axis"] for c in
                                                   v.get("symmetries_continuous", [])]}
                           for k, v in info.items() if int(k) in YCBV_SYMMETRIC_OBJ_IDS}}


def _factor_depth(root: Path, name: str) -> float:
    import scipy.io

    meta = scipy.io.loadmat(root / f"{name}-meta.mat", variable_names=("factor_depth",))
    return float(np.asarray(meta["factor_depth"]).ravel()[0])


def convert_demo(out: str | Path, *, rng: int = 0, split: str = "test") -> dict[str, Any]:
    """Write the synthetic demo scene (:func:`certpose.data.synthetic.make_mug_scene`) as a
    BOP folder: one image (scene 0, image 0) with the mug as object 1 (its mesh, with its
    axial symmetry left out: the handle breaks it), millimetre depth (``depth_scale`` 1)."""
    import imageio.v3 as iio

    from certpose.bop.render import MeshDepthRenderer
    from certpose.data.synthetic import make_mug_scene

    out = Path(out)
    sc = make_mug_scene(rng=rng)
    mesh = sc.model_mesh()
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.triangles, dtype=np.int64)
    write_bop_ply(out / "models" / "obj_000001.ply", V * MM, F)
    write_bop_json(out / "models" / "models_info.json", {"1": model_info(V, symmetric=False)})
    sdir = out / split / f"{0:06d}"
    (sdir / "rgb").mkdir(parents=True, exist_ok=True)
    (sdir / "depth").mkdir(parents=True, exist_ok=True)
    iio.imwrite(sdir / "rgb" / "000000.png", sc.frame.color)
    iio.imwrite(sdir / "depth" / "000000.png",
                np.clip(np.rint(sc.frame.depth * MM), 0, 65535).astype(np.uint16))
    _write_mask(sdir / "mask_visib" / "000000_000000.png", sc.object_mask)
    K = sc.intrinsics.K
    T = sc.T_camera_object
    write_bop_json(sdir / "scene_camera.json",
                   {"0": {"cam_K": [float(v) for v in K.ravel()], "depth_scale": 1.0}})
    write_bop_json(sdir / "scene_gt.json", {"0": [{
        "cam_R_m2c": [float(v) for v in T[:3, :3].ravel()],
        "cam_t_m2c": [float(v) * MM for v in T[:3, 3]], "obj_id": 1}]})
    sil = MeshDepthRenderer(V, F).depth(T, K, sc.object_mask.shape) > 0
    n_all, n_vis = int(sil.sum()), int(sc.object_mask.sum())
    write_bop_json(sdir / "scene_gt_info.json", {"0": [{
        "bbox_obj": _bbox(sil), "bbox_visib": _bbox(sc.object_mask), "px_count_all": n_all,
        "px_count_valid": int((sil & (sc.frame.depth > 0)).sum()), "px_count_visib": n_vis,
        "visib_fract": min(1.0, n_vis / max(n_all, 1))}]})
    write_bop_json(out / f"{split}_targets_bop19.json",
                   [{"im_id": 0, "inst_count": 1, "obj_id": 1, "scene_id": 0}])
    return {"images": 1, "instances": 1, "targets": 1, "objects": [1], "out": str(out)}
