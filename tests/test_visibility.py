"""Eq. (1) scores what the camera sees: the self-occlusion table, the visibility-blended kernels,
a faithful surface (convex hull, meshes), and a box seen from one side."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose.geometry.features import FPFHBackbone
from certpose.geometry.objects import object_from_points, sample_mesh, sample_surface
from certpose.geometry.rgbd import CameraIntrinsics, RGBDFrame
from certpose.model.classifier import classify_from_mask
from certpose.model.likelihood import LikelihoodParams, PoseLikelihood
from certpose.model.scene import build_scene_field
from certpose.model.visibility import cube_directions, visibility_table

from .conftest import box_surface, require_data


def _face_areas(points: np.ndarray, normals: np.ndarray, areas: np.ndarray) -> np.ndarray:
    """Area on each of an axis-aligned box's six faces, by the samples' normals: (3, 2)."""
    out = np.zeros((3, 2))
    for a in range(3):
        out[a, 0] = areas[normals[:, a] > 0.9].sum()
        out[a, 1] = areas[normals[:, a] < -0.9].sum()
    return out


def test_an_unevenly_sampled_box_keeps_equal_opposite_faces() -> None:
    # One large face sampled four times as densely as its opposite: the reconstructed surface
    # must still give both the area the box gives them.
    rng = np.random.default_rng(0)
    size = np.array([0.08, 0.16, 0.21])
    pts = box_surface(rng, size, 300)
    dense = box_surface(rng, size, 1200)
    pts = np.concatenate([pts, dense[np.isclose(dense[:, 0], size[0] / 2)]])
    p, n, a = sample_surface(pts, voxel_size=0.005)
    faces = _face_areas(p, n, a)
    want = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]])
    np.testing.assert_allclose(faces[:, 0], faces[:, 1], rtol=0.02)
    np.testing.assert_allclose(faces.mean(axis=1), want, rtol=0.05)


def test_a_concave_object_is_not_replaced_by_its_hull() -> None:
    # An L-shaped prism: its hull would fill the notch.
    rng = np.random.default_rng(1)
    a = box_surface(rng, np.array([0.1, 0.04, 0.06]), 600) + [0.0, -0.03, 0.0]
    b = box_surface(rng, np.array([0.04, 0.1, 0.06]), 600) + [-0.03, 0.0, 0.0]
    pts = np.concatenate([a, b])
    inside = lambda q, c, s: np.all(np.abs(q - c) < s / 2 - 1e-4, axis=1)  # noqa: E731
    pts = pts[~(inside(pts, [0.0, -0.03, 0.0], np.array([0.1, 0.04, 0.06]))
                & ~inside(pts, [-0.03, 0.0, 0.0], np.array([0.04, 0.1, 0.06])))]
    pts = pts[~inside(pts, [0.0, -0.03, 0.0], np.array([0.1, 0.04, 0.06]))
              | ~inside(pts, [-0.03, 0.0, 0.0], np.array([0.04, 0.1, 0.06]))]
    p, _, _ = sample_surface(pts, voxel_size=0.005)
    # No sample in the notch's corner region (x > 0.01, y > 0.01), which the hull would cover.
    assert not np.any((p[:, 0] > 0.015) & (p[:, 1] > 0.015))


def test_a_mesh_is_sampled_itself() -> None:
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_box(0.05, 0.1, 0.2)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    p, n, a = sample_mesh((V, F), voxel_size=0.005)
    assert a.sum() == pytest.approx(mesh.get_surface_area(), rel=1e-6)
    faces = _face_areas(p, n, a)
    np.testing.assert_allclose(faces[:, 0], faces[:, 1], rtol=0.02)
    obj = object_from_points(V, FPFHBackbone(), voxel_size=0.005, mesh=(V, F))
    assert obj.areas.sum() == pytest.approx(mesh.get_surface_area(), rel=1e-6)
    with pytest.raises(ValueError, match="triangles"):
        sample_mesh((V, F + 100), voxel_size=0.005)


def test_read_mesh_reads_triangles_and_refuses_point_clouds(tmp_path) -> None:  # noqa: ANN001
    import open3d as o3d

    from certpose.io.points import read_mesh

    mesh = o3d.geometry.TriangleMesh.create_box(0.05, 0.1, 0.2)
    o3d.io.write_triangle_mesh(str(tmp_path / "box.ply"), mesh)
    o3d.io.write_triangle_mesh(str(tmp_path / "box.obj"), mesh)
    for name in ("box.ply", "box.obj"):
        V, F = read_mesh(tmp_path / name)
        assert F.shape[1] == 3 and F.shape[0] == 12 and V.shape[1] == 3
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).random((10, 3))))
    o3d.io.write_point_cloud(str(tmp_path / "cloud.ply"), pcd)
    assert read_mesh(tmp_path / "cloud.ply") is None
    np.savetxt(tmp_path / "pts.xyz", np.zeros((4, 3)))
    assert read_mesh(tmp_path / "pts.xyz") is None
    with pytest.raises(FileNotFoundError):
        read_mesh(tmp_path / "missing.ply")


def _mug_like(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A closed cylinder (radius 4 cm, height 9 cm) with a box handle on +x: points, normals."""
    import open3d as o3d

    body = o3d.geometry.TriangleMesh.create_cylinder(0.04, 0.09, resolution=64)
    handle = o3d.geometry.TriangleMesh.create_box(0.025, 0.012, 0.05)
    handle.translate([0.045, -0.006, -0.025])
    mesh = body + handle
    p, n, _ = sample_mesh(mesh, voxel_size=0.004, rng=rng)
    return p, n


def test_the_body_hides_the_handle_from_the_other_side() -> None:
    p, n = _mug_like(np.random.default_rng(2))
    vt = visibility_table(p, n)
    assert vt.table is not None  # not convex
    handle = p[:, 0] > 0.047
    far = 5.0
    behind = vt.visibility(p, [-far, 0.0, 0.0])
    front = vt.visibility(p, [far, 0.0, 0.0])
    assert behind[handle].max() == 0.0
    # From +x the handle shows its end face (normal +x) square on; its sides are edge-on.
    end = handle & (n[:, 0] > 0.9)
    assert end.sum() > 10 and np.median(front[end]) == 1.0
    # The body's far half is hidden, its near half seen square on.
    body = np.linalg.norm(p[:, :2], axis=1) > 0.039
    assert front[body & (p[:, 0] < -0.02)].max() == 0.0
    assert np.median(front[body & (p[:, 0] > 0.03) & ~handle]) == 1.0


def test_a_convex_surface_needs_no_table_and_hides_only_its_back() -> None:
    rng = np.random.default_rng(3)
    p, n, _ = sample_surface(box_surface(rng, np.array([0.05, 0.08, 0.1]), 400), voxel_size=0.005)
    vt = visibility_table(p, n)
    assert vt.table is None
    v = vt.visibility(p, [0.0, 0.0, 2.0])
    np.testing.assert_array_equal(v[n[:, 2] > 0.9], 1.0)
    np.testing.assert_array_equal(v[n[:, 2] < -0.02], 0.0)  # the back and the far-leaning sides


def test_cube_directions_cover_the_sphere_with_a_ring_past_each_face() -> None:
    d = cube_directions(4)
    assert d.shape == (6, 6, 6, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    # The ring cells of face +x look past its edge, into the neighbouring faces' region.
    assert np.all(np.abs(d[0, 0, :, 1]) > np.abs(d[0, 1, :, 1]))


# A synthetic frame: a box on a table seen from one side (exact depth, no noise).
_K = CameraIntrinsics(500.0, 500.0, 159.5, 119.5, 320, 240)


def _box_scene(size=(0.06, 0.12, 0.18)):
    """Depth image of a box (pose T_camera_object) in front of a wall; the box's mask."""
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(*size)
    box.translate(-np.asarray(size) / 2)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [20, 35, 10], degrees=True).as_matrix()
    T[:3, 3] = [0.0, 0.0, 0.7]
    posed = o3d.geometry.TriangleMesh(box)
    posed.transform(T)
    wall = o3d.geometry.TriangleMesh.create_box(2.0, 2.0, 0.01)
    wall.translate([-1.0, -1.0, 1.0])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(wall))
    obj_id = scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(posed))
    u, v = np.meshgrid(np.arange(_K.width), np.arange(_K.height))
    dirs = np.stack([(u - _K.cx) / _K.fx, (v - _K.cy) / _K.fy, np.ones_like(u, dtype=float)], -1)
    rays = np.concatenate([np.zeros_like(dirs), dirs], -1).reshape(-1, 6).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    depth = hit["t_hit"].numpy().reshape(_K.height, _K.width).astype(np.float64)
    mask = hit["geometry_ids"].numpy().reshape(_K.height, _K.width) == obj_id
    frame = RGBDFrame(None, np.where(np.isfinite(depth), depth, 0.0), _K)
    return frame.with_mask(mask), T, box


def test_a_box_seen_from_one_side_does_not_prefer_its_flip() -> None:
    frame, T, box = _box_scene()
    backbone = FPFHBackbone()
    scene = build_scene_field([frame], backbone, voxel_size=0.005)
    cls = classify_from_mask(scene, frame)
    # The model sampled unevenly: the large face the camera does not see (an x face) four times
    # as densely as the one it sees; the paper's eq. (1) on a surface that keeps the unevenness
    # then prefers the flips that show the dense face by about 1000 nats.
    rng = np.random.default_rng(4)
    size = np.array([0.06, 0.12, 0.18])
    hidden_side = -np.sign(T[:3, 0] @ -T[:3, 3])
    pts = box_surface(rng, size, 250)
    dense = box_surface(rng, size, 1000)
    pts = np.concatenate([pts, dense[np.isclose(dense[:, 0], hidden_side * size[0] / 2)]])
    obj = object_from_points(pts, backbone, voxel_size=0.005)
    lik = PoseLikelihood(scene, cls, obj)
    assert lik.visible
    truth = float(lik(T))
    flips = []
    for axis in np.eye(3):
        F = np.eye(4)
        F[:3, :3] = Rotation.from_rotvec(np.pi * axis).as_matrix()
        flips.append(float(lik(T @ F)))
    # The box is symmetric under the three flips: none may beat the truth by more than the
    # scatter of eq. (1) over sampling seeds (about 1-2% of the ~1,500 visible units).
    assert max(flips) - truth < 40.0
    blind = PoseLikelihood(scene, cls, obj, params=replace(LikelihoodParams(), visibility=False))
    assert not blind.visible


def test_kernels_agree_with_point_terms_and_the_numpy_visibility() -> None:
    frame, T, _ = _box_scene()
    backbone = FPFHBackbone()
    scene = build_scene_field([frame], backbone, voxel_size=0.005)
    cls = classify_from_mask(scene, frame)
    p, n = _mug_like(np.random.default_rng(5))
    from certpose.geometry.objects import ObjectModel

    d = backbone.describe(p, normals=n)
    obj = ObjectModel(p, d, None, n, "mug-like")
    lik = PoseLikelihood(scene, cls, obj)
    blind = PoseLikelihood(scene, cls, obj, params=LikelihoodParams(visibility=False))
    rng = np.random.default_rng(6)
    poses = np.stack([T @ np.block([[Rotation.random(random_state=rng).as_matrix(), rng.normal(scale=0.01, size=(3, 1))],
                                    [np.zeros((1, 3)), np.ones((1, 1))]]) for _ in range(40)])
    batch = lik(poses)
    for k in (0, 7, 39):
        terms = lik.point_terms(poses[k])
        assert terms.sum() == pytest.approx(batch[k], rel=1e-9, abs=1e-6)
        # Blend: v * (the blind term without free space) + (1 - v) * log_p_unobserved + free space.
        v = lik.visibility_table.visibility(p, np.linalg.inv(poses[k])[:3, :3] @ np.zeros(3)
                                            + np.linalg.inv(poses[k])[:3, 3])
        blind_terms = blind.point_terms(poses[k])
        free = lik._free_charge() * lik._pixels.fractions(poses[k], p)
        want = v * (blind_terms - free) + (1 - v) * lik.params.log_p_unobserved + free
        np.testing.assert_allclose(terms, want, atol=1e-5)
        assert lik.visible_weight(poses[k]) == pytest.approx(v.sum(), rel=1e-9)
        # The per-point visibility in the model's order, and the weights it multiplies.
        np.testing.assert_allclose(lik.visibility(poses[k]), v, atol=1e-12)
        np.testing.assert_array_equal(lik.point_weights, np.ones(len(p)))
        np.testing.assert_array_equal(blind.visibility(poses[k]), np.ones(len(p)))


def test_stencil_batches_of_a_seen_object_score_each_pose_as_alone_bit_for_bit() -> None:
    # The visibility kernel (and the per-pixel free space beside it) on a refinement's batches:
    # finite-difference stencils around several poses near the truth, where the kernels reuse
    # a point's corner values across the poses of a block and skip the pixels of points behind
    # the measured depth. Each pose's value is the one it gets alone, bit for bit, with and
    # without visibility.
    frame, T, _ = _box_scene()
    backbone = FPFHBackbone()
    scene = build_scene_field([frame], backbone, voxel_size=0.005)
    cls = classify_from_mask(scene, frame)
    p, n = _mug_like(np.random.default_rng(5))
    from certpose.geometry.objects import ObjectModel

    obj = ObjectModel(p, backbone.describe(p, normals=n), None, n, "mug-like")
    rng = np.random.default_rng(8)
    poses = []
    for _ in range(4):
        T0 = T @ np.block([[Rotation.from_rotvec(rng.normal(scale=0.05, size=3)).as_matrix(),
                            rng.normal(scale=0.005, size=(3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
        for sign in (1.0, -1.0):
            for axis in range(6):
                x = np.zeros(6)
                x[axis] = sign * 0.003 if axis < 3 else sign * 0.03
                D = np.eye(4)
                D[:3, :3] = Rotation.from_rotvec(x[3:]).as_matrix()
                D[:3, 3] = x[:3]
                poses.append(T0 @ D)
    poses = np.stack(poses)
    for params in (LikelihoodParams(), LikelihoodParams(visibility=False)):
        lik = PoseLikelihood(scene, cls, obj, params=params)
        assert lik.visible == params.visibility and lik._pixels is not None
        alone = np.array([lik(P) for P in poses])
        np.testing.assert_array_equal(lik(poses), alone)
        assert np.ptp(alone) > 1.0


def test_real_frame_cracker_box_truth_beats_its_flips() -> None:
    from certpose.estimation.pipeline import ycbv_setup

    s = ycbv_setup(require_data("ycbv"), "0050/000001", "003_cracker_box")
    lik = PoseLikelihood(s.scene, s.classification, s.object_model)
    G = s.frame.poses["003_cracker_box"]
    c = s.object_model.points.mean(axis=0)
    axes = np.linalg.eigh(np.cov((s.object_model.points - c).T))[1]
    truth = float(lik(G))
    for k in range(3):
        F = np.eye(4)
        F[:3, :3] = Rotation.from_rotvec(np.pi * axes[:, k]).as_matrix()
        F[:3, 3] = c - F[:3, :3] @ c
        assert float(lik(G @ F)) < truth


def test_explained_fraction_of_the_truth_and_of_a_pose_13_cm_off() -> None:
    from certpose.estimation.mle import EXPLAINED, explained_fraction
    from certpose.estimation.pipeline import ycbv_setup
    from certpose.model.grid import scene_grid_spec

    s = ycbv_setup(require_data("ycbv"), "0050/000001", "006_mustard_bottle")
    grid = scene_grid_spec(s.scene)
    G = s.frame.poses["006_mustard_bottle"]
    assert explained_fraction(s.classification, s.object_model, G, grid) > 0.9
    off = G.copy()
    off[:3, 3] += [0.13, 0.0, 0.0]
    assert explained_fraction(s.classification, s.object_model, off, grid) < EXPLAINED["mask"]


@pytest.mark.slow
def test_a_pose_that_leaves_most_positives_unexplained_is_not_converged() -> None:
    # The classifier marks the mug and the two objects beside it (their masks' union): whatever
    # the mug's pose, most positives lie elsewhere; the result must say so instead of
    # "converged". The mug's own mask gives "converged".
    from certpose.estimation.mle import MLEStatus, estimate_mle
    from certpose.estimation.pipeline import ycbv_setup

    s = ycbv_setup(require_data("ycbv"), "0000/000001", "025_mug")
    union = s.frame.label > 0
    cls = classify_from_mask(s.scene, s.frame.frame.with_mask(union))
    res = estimate_mle(s.scene, cls, s.object_model, rng=0)
    assert res.status is MLEStatus.UNEXPLAINED and not res.success
    assert "explains only" in res.message
    res = estimate_mle(s.scene, s.classification, s.object_model, rng=0)
    assert res.status is MLEStatus.CONVERGED


@pytest.mark.slow
def test_the_demos_upside_down_mug_scores_far_below_the_truth() -> None:
    # Exact geometry, no sensor noise: the mug turned upside down (a half turn about a horizontal
    # axis, refined) scores below the upright truth. About the handle's axis (x) the upturned mug
    # shows the camera nearly the same silhouette: measured 14.7 nats below with the default
    # windows (75 with no min-filter at all, where real frames' silhouettes fail the truth);
    # about y the handle swaps sides: 87 nats below.
    from certpose.estimation.batch import refine_poses
    from certpose.estimation.pipeline import PoseParams, run_demo
    from certpose.sampling.target import demo_object_model

    res = run_demo(params=replace(PoseParams(), sampler=None), rng=0)
    obj = demo_object_model()
    lik = PoseLikelihood(res.scene, res.classification, obj)
    T_w = res.T_world_camera
    G = T_w @ res.T_camera_object_gt
    truth = float(refine_poses(lik, G[None], scale=obj.radius)[1][0])
    c = obj.points.mean(axis=0)
    margins = []
    for axis in (np.array([1.0, 0, 0]), np.array([0, 1.0, 0])):  # the mug's axis is z
        F = np.eye(4)
        F[:3, :3] = Rotation.from_rotvec(np.pi * axis).as_matrix()
        F[:3, 3] = c - F[:3, :3] @ c
        _, v = refine_poses(lik, (G @ F)[None], scale=obj.radius)
        margins.append(truth - float(v[0]))
    assert margins[0] > 100.0 and margins[1] > 100.0, margins


def _demo_refined_tilt(seed: int, params: LikelihoodParams) -> float:
    """Tilt (deg) of the demo mug's axis at eq. (1)'s best local climb (the MLE's compass
    polish) from the truth and from the truth tilted by 2 deg in 8 directions, with the
    demo's view-built model."""
    from certpose.data.synthetic import make_mug_scene
    from certpose.estimation.batch import polish_poses
    from certpose.estimation.pipeline import PoseParams
    from certpose.sampling.target import demo_object_model

    pp = PoseParams()
    sc = make_mug_scene(rng=seed)
    scene = build_scene_field(sc.frame, FPFHBackbone(), voxel_size=pp.voxel_size, roi_mask=sc.object_mask,
                              margin=pp.roi_margin)
    cls = classify_from_mask(scene, sc.frame.with_mask(sc.object_mask), params=pp.classifier)
    obj = demo_object_model()
    lik = PoseLikelihood(scene, cls, obj, params=params)
    G = np.asarray(sc.T_camera_object, dtype=np.float64)
    starts = [G]
    for a in np.arange(8) * np.pi / 4:
        T = G.copy()
        w = np.radians(2.0) * np.array([np.cos(a), np.sin(a), 0.0])
        T[:3, :3] = G[:3, :3] @ Rotation.from_rotvec(w).as_matrix()
        starts.append(T)
    Ts, vs, _ = polish_poses(lik, np.stack(starts), scale=obj.radius, step=0.02, min_step=2e-4, max_iter=400)
    axis = Ts[int(np.argmax(vs))][:3, :3] @ np.array([0.0, 0.0, 1.0])
    return float(np.degrees(np.arccos(np.clip(axis @ G[:3, 2], -1.0, 1.0))))


@pytest.mark.slow
def test_the_demos_view_built_mug_is_not_tilted() -> None:
    # The demo's model from views has no inside: its 3.5-mm wall is averaged into one sheet at
    # the 5-mm voxel. Scoring every model point (the paper's eq. (1), visibility off), the back
    # of that sheet stands in for the inner wall the camera sees through the opening and eq.
    # (1) tilts the mug by 1.7-2.8 deg on seeds 0-4 (15-31 nats over the best upright pose);
    # exact mesh samples 0.1-2.3 deg (0-8 nats). Scoring only what the camera sees: 0.5-1.9
    # deg (mesh 0.7-1.1; examples/benchmarks/bench_model_tilt.py). This climb on seed 0:
    # 0.55 deg, and 2.50 with visibility off; the model from views above only (no bottom)
    # tilted 1.49 deg with visibility.
    assert _demo_refined_tilt(0, LikelihoodParams()) < 1.2
