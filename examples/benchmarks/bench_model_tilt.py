"""The demo mug's axis tilt that eq. (1) prefers with the view-built model and with exact mesh samples.

For each demo seed (``certpose pose --demo``'s scene: exact renders, no noise) eq. (1) is
refined locally from the ground truth (the best of :func:`certpose.estimation.mle.refine_pose`
from the truth and of the MLE's compass polish :func:`certpose.estimation.batch.polish_poses`
from it and from 24 starts tilted by 1-3 deg) with each object model (``--variants``):

* ``views``: the demo's model, :func:`certpose.sampling.target.demo_object_model` (four posed
  renders, the body sampled with its revolution symmetry);
* ``mesh``: the exact mesh of the synthetic mug sampled (``object_from_points(mesh=...)``,
  the body sampled with its symmetry too);
* ablations: ``views-norev`` / ``mesh-norev`` (no revolution resampling), ``views-snapped``
  (the view-built points moved onto the exact mesh), ``views-exact-normals``,
  ``mesh-view-desc`` (mesh samples with the view-built model's descriptors),
  ``mesh-no-inside`` (without the inner wall and inner bottom), ``views-mesh-inside`` (the
  view-built model plus the mesh's inside), ``views-fuse*mm`` (the views fused at a finer voxel
  than the scene's), ``mesh-views-coverage``.

Printed per seed and model: the model's area by region of the mug, the refined pose's tilt of the
axis from the truth (deg), its turn about the axis and translation offset, and eq. (1) at the
refined pose minus at the truth and minus at the best upright pose (the axis kept, the turn and
translation refined), each split into its terms: descriptor similarity (``beta f^T z``), the
classifier's ``log p_O`` of visible points, the free-space charge, and the unobserved prior of
hidden points. ``--profile``: eq. (1) at fixed tilts towards the refined one. ``--set``:
:class:`~certpose.model.likelihood.LikelihoodParams` overrides (e.g. ``visibility=False``, the
paper's eq. (1) scoring every point). The figures are in ``docs/benchmarks/pose.md``.

Usage::

    python examples/benchmarks/bench_model_tilt.py [--seeds 0 1 2 3 4] [--variants views mesh ...]
        [--profile] [--set visibility=False]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from typing import Any

import numpy as np

AXIS = np.array([0.0, 0.0, 1.0])


def demo_problem(seed: int) -> tuple[Any, Any, Any, Any]:
    """The demo scene of ``seed``: (synthetic scene, scene field, classifier, pose params)."""
    from certpose.data.synthetic import make_mug_scene
    from certpose.estimation.pipeline import PoseParams, _scene_for
    from certpose.geometry.features import FPFHBackbone
    from certpose.model.classifier import classify_from_mask

    params = PoseParams()
    sc = make_mug_scene(rng=np.random.default_rng(seed))
    scene = _scene_for(sc.frame, sc.object_mask, params, FPFHBackbone())
    cls = classify_from_mask(scene, sc.frame.with_mask(sc.object_mask), params=params.classifier)
    return sc, scene, cls, params


def mesh_model(*, revolution: str | None = "auto") -> Any:
    """The synthetic mug's exact mesh, sampled as ``object_from_points(mesh=...)`` does."""
    from certpose.data.synthetic import make_mug_scene
    from certpose.geometry.features import FPFHBackbone
    from certpose.geometry.objects import object_from_points

    sc = make_mug_scene(rng=0)
    mesh = sc.model_mesh()
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    return object_from_points(sc.model_points, FPFHBackbone(), voxel_size=0.005, name="mug-mesh",
                              mesh=(V, F), revolution=revolution)


def view_model(**options: Any) -> Any:
    from certpose.sampling.target import demo_object_model

    return demo_object_model(**options)


def _mug_mesh() -> Any:
    from certpose.data.synthetic import make_mug_scene

    return make_mug_scene(rng=0).model_mesh()


def closest_on_mesh(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nearest points of the exact mug mesh to ``points`` and the mesh's normals there."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(_mug_mesh()))
    ans = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    q = ans["points"].numpy().astype(np.float64)
    n = ans["primitive_normals"].numpy().astype(np.float64)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    # Outwards: the body's triangles face either way (a lathe); turn them away from the axis
    # and the body's centre on its outer surface.
    return q, n


def with_parts(obj: Any, **fields: Any) -> Any:
    """``obj`` with some of its fields replaced (points, normals, descriptors, areas)."""
    from certpose.geometry.objects import ObjectModel

    f = {k: getattr(obj, k) for k in ("points", "descriptors", "colors", "normals", "name", "areas")}
    f.update(fields)
    return ObjectModel(**f)


def views_exact_normals() -> Any:
    """The view-built model with each point's normal the exact mesh's (sign kept)."""
    obj = view_model()
    _, n = closest_on_mesh(obj.points)
    n = np.where(np.sum(n * obj.normals, axis=1, keepdims=True) < 0, -n, n)
    return with_parts(obj, normals=n)


def views_snapped() -> Any:
    """The view-built model with its points moved onto the exact mesh (normals kept)."""
    obj = view_model()
    q, _ = closest_on_mesh(obj.points)
    return with_parts(obj, points=q)


def views_fine_fusion(fuse_voxel: float = 0.002) -> Any:
    """The view-built model from the views' cloud averaged per ``fuse_voxel`` instead of the
    scene's 5-mm voxel (then sampled at 5 mm as the demo does)."""
    from certpose.geometry.features import FPFHBackbone
    from certpose.geometry.objects import fuse_views, object_from_points

    sc_views = _views()
    fused = fuse_views(sc_views, voxel_size=fuse_voxel, normals=False)
    return object_from_points(fused.points, FPFHBackbone(), voxel_size=0.005, colors=fused.colors,
                              name="mug", revolution="auto")


def _views() -> Any:
    from certpose.data.synthetic import make_mug_scene

    return make_mug_scene(rng=0).render_object_views(4)


def views_from_above() -> Any:
    """The view-built model from four views 30 deg above the equator only (no bottom)."""
    from certpose.data.synthetic import make_mug_scene
    from certpose.geometry.features import FPFHBackbone
    from certpose.geometry.objects import object_from_views

    views = make_mug_scene(rng=0).render_object_views(4, elevation_deg=30.0)
    return object_from_views(views, FPFHBackbone(), voxel_size=0.005, name="mug", revolution="auto")


def mesh_view_descriptors() -> Any:
    """Exact mesh samples whose descriptors are the view-built model's nearest point's."""
    from scipy.spatial import cKDTree

    mesh, views = mesh_model(), view_model()
    j = cKDTree(views.points).query(mesh.points)[1]
    return with_parts(mesh, descriptors=views.descriptors[j])


def mesh_views_coverage(reach: float = 0.004) -> Any:
    """Exact mesh samples where the view-built model has a point within ``reach`` (m): the
    mesh restricted to the surface the views' model covers."""
    from scipy.spatial import cKDTree

    mesh, views = mesh_model(), view_model()
    d = cKDTree(views.points).query(mesh.points)[0]
    return mesh.select(d <= reach)


def region_areas(obj: Any) -> dict[str, float]:
    """The model's area (cm^2) by region of the mug: outer wall, inner wall, outer bottom,
    inner bottom, rim, handle."""
    from certpose.data.synthetic import MUG_BOTTOM, MUG_HEIGHT, MUG_INNER_RADIUS, MUG_RADIUS

    p = obj.points
    a = obj.areas if obj.areas is not None else np.full(len(p), 0.005**2)
    r, z, h = np.hypot(p[:, 0], p[:, 1]), p[:, 2], MUG_HEIGHT / 2
    handle = r > MUG_RADIUS + 0.002
    rim = ~handle & (z > h - 0.002)
    bottom = ~handle & ~rim & (z < -h + 0.002)
    inner_bottom = ~handle & ~rim & ~bottom & (z < -h + MUG_BOTTOM + 0.002) & (r < MUG_INNER_RADIUS - 0.002)
    rest = ~(handle | rim | bottom | inner_bottom)
    inner = rest & (r < (MUG_RADIUS + MUG_INNER_RADIUS) / 2)
    outer = rest & ~inner
    parts = {"outer": outer, "inner": inner, "bottom": bottom, "in-bottom": inner_bottom, "rim": rim,
             "handle": handle}
    return {k: 1e4 * float(a[m].sum()) for k, m in parts.items()}


def mesh_without_inside() -> Any:
    """Exact mesh samples without the mug's inside (inner wall and inner bottom)."""
    obj = mesh_model()
    from certpose.data.synthetic import MUG_INNER_RADIUS, MUG_RADIUS

    p = obj.points
    r = np.hypot(p[:, 0], p[:, 1])
    inside = (r < (MUG_RADIUS + MUG_INNER_RADIUS) / 2) & (p[:, 2] > -0.049) & (p[:, 2] < 0.049)
    return obj.select(~inside)


def views_with_mesh_inside(depth: float | None = None) -> Any:
    """The view-built model plus the exact mesh samples of the mug's inside (what it lacks);
    with ``depth`` (m) only the inner wall's band that deep below the rim (what views 30 deg
    above the equator see of it, turned about the axis: 42 mm)."""
    from certpose.data.synthetic import MUG_HEIGHT
    from certpose.geometry.objects import ObjectModel

    views, mesh = view_model(), mesh_model()
    keep = ~_outside(mesh.points)
    if depth is not None:
        keep &= mesh.points[:, 2] > MUG_HEIGHT / 2 - depth
    inside = mesh.select(keep)
    cat = {k: np.concatenate([getattr(views, k), getattr(inside, k)])
           for k in ("points", "descriptors", "normals", "areas")}
    return ObjectModel(name="mug", **cat)


def _outside(p: np.ndarray) -> np.ndarray:
    from certpose.data.synthetic import MUG_INNER_RADIUS, MUG_RADIUS

    r = np.hypot(p[:, 0], p[:, 1])
    return ~((r < (MUG_RADIUS + MUG_INNER_RADIUS) / 2) & (p[:, 2] > -0.049) & (p[:, 2] < 0.049))


#: Models by name: a callable returning an ObjectModel.
VARIANTS: dict[str, Any] = {
    "views": lambda: view_model(),
    "mesh": lambda: mesh_model(),
    "views-norev": lambda: view_model(revolution=None),
    "mesh-norev": lambda: mesh_model(revolution=None),
    "views-exact-normals": views_exact_normals,
    "views-snapped": views_snapped,
    "views-fuse2mm": views_fine_fusion,
    "mesh-view-desc": mesh_view_descriptors,
    "mesh-views-coverage": mesh_views_coverage,
    "mesh-no-inside": mesh_without_inside,
    "views-mesh-inside": views_with_mesh_inside,
    "views-mesh-band": lambda: views_with_mesh_inside(0.042),
    "views-above": views_from_above,
    "views-fuse2.5mm": lambda: views_fine_fusion(0.0025),
    "views-fuse1.5mm": lambda: views_fine_fusion(0.0015),
    "views-fuse1mm": lambda: views_fine_fusion(0.001),
}


def refine(lik: Any, T0: np.ndarray, scale: float) -> tuple[np.ndarray, float]:
    """The best of local climbs of eq. (1) from ``T0`` and from ``T0`` tilted by 1, 2 and 3 deg
    in 8 directions: the MLE's refinement (:func:`~certpose.estimation.mle.refine_pose`) from
    ``T0``, then the MLE's compass polish (:func:`~certpose.estimation.batch.polish_poses`) of
    all 25 starts (the objective is piecewise linear: one climb can stop on a ledge)."""
    from scipy.spatial.transform import Rotation

    from certpose.estimation.batch import polish_poses
    from certpose.estimation.mle import refine_pose

    T1, _, _ = refine_pose(lik, T0, scale=scale, max_step=0.5)
    starts = [T1]
    for deg in (1.0, 2.0, 3.0):
        for a in np.arange(8) * np.pi / 4:
            T = T0.copy()
            T[:3, :3] = T0[:3, :3] @ Rotation.from_rotvec(np.radians(deg) * np.array(
                [np.cos(a), np.sin(a), 0.0])).as_matrix()
            starts.append(T)
    Ts, vs, _ = polish_poses(lik, np.stack(starts), scale=scale, step=0.02, min_step=2e-4,
                             max_iter=400)
    i = int(np.argmax(vs))
    return Ts[i], float(vs[i])


def climb_at_tilt(lik: Any, T0: np.ndarray, scale: float, *, step: float = 0.02,
                  min_step: float = 2e-4, max_iter: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Compass search of eq. (1) from each of ``T0`` (H, 4, 4) over the turn about the model's
    axis and the translation only: the axis keeps its direction (the profile of eq. (1) at the
    tilt of each start)."""
    from certpose.estimation.batch import polish_poses

    held = np.eye(6)[[0, 1, 2, 5]]  # rho x, y, z (object frame), omega about z
    T, values, _ = polish_poses(lik, T0, scale=scale, step=step, min_step=min_step, max_iter=max_iter,
                                axes=np.vstack([held, -held]))
    return T, values


def upright(T: np.ndarray, G: np.ndarray) -> np.ndarray:
    """``T`` turned (about the model's centre of rotation, the origin) so that its axis is
    ``G``'s again, by the least rotation."""
    from scipy.spatial.transform import Rotation

    a, b = T[:3, :3] @ AXIS, G[:3, :3] @ AXIS
    w = np.cross(a, b)
    s = np.linalg.norm(w)
    if s < 1e-12:
        return T.copy()
    R = Rotation.from_rotvec(w / s * np.arctan2(s, a @ b)).as_matrix()
    out = T.copy()
    out[:3, :3] = R @ T[:3, :3]
    return out


def tilted(T: np.ndarray, G: np.ndarray, direction: np.ndarray, deg: float) -> np.ndarray:
    """``T`` straightened to ``G``'s axis, then tilted by ``deg`` towards ``direction`` (a unit
    vector of ``G``'s object frame, normal to the axis), about the object's origin."""
    from scipy.spatial.transform import Rotation

    w = np.cross(AXIS, direction)
    w /= np.linalg.norm(w)
    U = upright(T, G)
    R = G[:3, :3] @ Rotation.from_rotvec(np.radians(deg) * w).as_matrix() @ G[:3, :3].T
    out = U.copy()
    out[:3, :3] = R @ U[:3, :3]
    return out


#: Tilts (deg) of the profile ``--profile`` prints.
PROFILE_TILTS = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5)


def tilt_profile(lik: Any, T: np.ndarray, G: np.ndarray, scale: float) -> np.ndarray:
    """Eq. (1) maximised over the turn about the axis and the translation at each of
    :data:`PROFILE_TILTS` towards the refined pose ``T``'s tilt (climbs from ``G`` and from
    ``T``, both tilted so)."""
    a = G[:3, :3].T @ (T[:3, :3] @ AXIS)
    d = a - (a @ AXIS) * AXIS
    d = d / np.linalg.norm(d) if np.linalg.norm(d) > 1e-9 else np.array([1.0, 0.0, 0.0])
    starts = [tilted(S, G, d, t) for t in PROFILE_TILTS for S in (G, T)]
    _, v = climb_at_tilt(lik, np.stack(starts), scale)
    return v.reshape(len(PROFILE_TILTS), 2).max(axis=1)


def term_split(scene: Any, cls: Any, obj: Any, lp: Any, T: np.ndarray) -> dict[str, float]:
    """Eq. (1) at ``T`` split into its terms (nats): descriptor, log p_O of visible points,
    free space, the unobserved prior of hidden points."""
    from certpose.model.likelihood import PoseLikelihood

    full = PoseLikelihood(scene, cls, obj, params=lp)
    no_desc = full.with_object(obj, params=replace(lp, beta=0.0))
    # c_empty at the unobserved prior: no free-space charge (voxels or pixels).
    bare = full.with_object(obj, params=replace(lp, beta=0.0, c_empty=lp.log_p_unobserved))
    f, nd, b = float(full(T)), float(no_desc(T)), float(bare(T))
    hidden = (bare.total_weight - bare.visible_weight(T)) * lp.log_p_unobserved
    return {"total": f, "desc": f - nd, "free": nd - b, "logp": b - hidden, "unobs": hidden}


def tilt_of(T: np.ndarray, G: np.ndarray) -> tuple[float, np.ndarray]:
    """Tilt (deg) of the model's axis at ``T`` from its axis at ``G``, and its direction in the
    object frame of ``G`` (unit, the axis at ``T`` seen from ``G``)."""
    a = G[:3, :3].T @ (T[:3, :3] @ AXIS)
    return float(np.degrees(np.arccos(np.clip(a @ AXIS, -1.0, 1.0)))), a


def run(seed: int, name: str, obj: Any, overrides: dict[str, Any] | None = None,
        profile: bool = False) -> dict[str, Any]:
    from certpose.model.likelihood import LikelihoodParams, PoseLikelihood

    sc, scene, cls, params = demo_problem(seed)
    lp = replace(params.likelihood or LikelihoodParams(), **(overrides or {}))
    lik = PoseLikelihood(scene, cls, obj, params=lp)
    G = np.array(sc.T_camera_object, dtype=np.float64)
    T, v = refine(lik, G, obj.radius)
    tilt, a = tilt_of(T, G)
    # The best upright pose: climbs at the truth's tilt from the truth and from T straightened.
    Us, uv = climb_at_tilt(lik, np.stack([G, upright(T, G)]), obj.radius)
    U, gain = Us[int(np.argmax(uv))], v - float(np.max(uv))
    at_T, at_G = term_split(scene, cls, obj, lp, T), term_split(scene, cls, obj, lp, G)
    at_U = term_split(scene, cls, obj, lp, U)
    diff = {k: at_T[k] - at_G[k] for k in at_T}
    over_upright = {k: at_T[k] - at_U[k] for k in at_T}
    az = float(np.degrees(np.arctan2(a[1], a[0])))
    # The turn about the axis (the hidden handle's arc is flat in it): the x axis' azimuth.
    x = G[:3, :3].T @ T[:3, :3] @ np.array([1.0, 0.0, 0.0])
    spin = float(np.degrees(np.arctan2(x[1], x[0])))
    # Direction of the tilt seen from the camera: the axis' move in the camera frame.
    move = T[:3, :3] @ AXIS - G[:3, :3] @ AXIS
    return {"seed": seed, "model": name, "tilt": tilt, "azimuth": az, "spin": spin, "move_cam": move,
            "shift_mm": 1000 * float(np.linalg.norm(T[:3, 3] - G[:3, 3])), "diff": diff, "gain": gain, "over_upright": over_upright,
            "profile": tilt_profile(lik, T, G, obj.radius) if profile else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--variants", nargs="+", default=["views", "mesh"], choices=sorted(VARIANTS))
    ap.add_argument("--profile", action="store_true",
                    help="also eq. (1) at fixed tilts towards the refined one (turn and translation refined)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="LikelihoodParams overrides (Python literals), e.g. visibility=False")
    args = ap.parse_args()
    import ast

    overrides = {k: ast.literal_eval(v) for k, v in (a.split("=", 1) for a in args.set)}
    for name in args.variants:
        t = time.perf_counter()
        obj = VARIANTS[name]()
        print(f"model {name}: {len(obj)} points, area {obj.area or 0:.5f} m^2 "
              f"({time.perf_counter() - t:.1f} s)", flush=True)
        print("  area by region (cm^2): " + ", ".join(f"{k} {v:.1f}" for k, v in region_areas(obj).items()),
              flush=True)
        tilts, gains = [], []
        for seed in args.seeds:
            r = run(seed, name, obj, overrides, args.profile)
            d = r["diff"]
            tilts.append(r["tilt"])
            print(f"  seed {seed}: tilt {r['tilt']:.2f} deg (towards azimuth {r['azimuth']:+.0f} deg "
                  f"of the object frame), spin {r['spin']:+.1f} deg, shift {r['shift_mm']:.2f} mm; eq. (1) refined - truth "
                  f"{d['total']:+.2f} nats = desc {d['desc']:+.2f} + log p_O {d['logp']:+.2f} "
                  f"+ free {d['free']:+.2f} + unobserved {d['unobs']:+.2f}", flush=True)
            u = r["over_upright"]
            print(f"          refined - best upright pose {r['gain']:+.2f} nats = desc {u['desc']:+.2f} "
                  f"+ log p_O {u['logp']:+.2f} + free {u['free']:+.2f} + unobserved {u['unobs']:+.2f}",
                  flush=True)
            gains.append(r["gain"])
            if r["profile"] is not None:
                p = r["profile"] - r["profile"][0]
                print("          profile towards the refined tilt (deg: nats over upright): "
                      + " ".join(f"{t:.1f}: {v:+.1f}" for t, v in zip(PROFILE_TILTS, p, strict=True)), flush=True)
        print(f"  {name}: tilt {min(tilts):.2f}-{max(tilts):.2f} deg (mean {np.mean(tilts):.2f}), "
              f"over upright {min(gains):.1f}-{max(gains):.1f} nats", flush=True)


if __name__ == "__main__":
    main()
