"""The embedded synthetic mug scene, checked against independent ray casts of its meshes."""

from __future__ import annotations

import numpy as np
import pytest

from certpose.data.synthetic import (
    HANDLE_CENTER_X,
    MUG_HEIGHT,
    MUG_RADIUS,
    make_mug_scene,
    mug_parts,
)
from solvers.lie import invert_transform


@pytest.fixture(scope="module")
def scene():
    return make_mug_scene(rng=7)


def _cast(meshes, intrinsics, T_camera_mesh):
    """z-depth image of the given object-frame meshes posed in the camera frame (inf = miss)."""
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    for mesh in meshes:
        m = o3d.geometry.TriangleMesh(mesh).transform(T_camera_mesh)
        rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
    v, u = np.mgrid[0 : intrinsics.height, 0 : intrinsics.width]
    d = np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones(u.shape)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    rays = np.concatenate([np.zeros_like(d), d], axis=-1).reshape(-1, 6).astype(np.float32)
    t = rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(u.shape)
    return t * d[..., 2]  # distance along a unit ray -> z-depth


def test_depth_at_the_mug_matches_the_ground_truth_mesh(scene):
    gt = _cast([scene.model_mesh()], scene.intrinsics, scene.T_camera_object)
    mask = scene.object_mask
    assert mask.sum() > 3000
    np.testing.assert_allclose(scene.frame.depth[mask], gt[mask], atol=1e-4)
    # Where the scene shows something else in front of the mug, it is closer than the mug.
    covered = np.isfinite(gt) & ~mask
    assert np.all(scene.frame.depth[covered] < gt[covered])


def test_handle_is_hidden(scene):
    handle = _cast([mug_parts()["handle"]], scene.intrinsics, scene.T_camera_object)
    in_view = np.isfinite(handle)
    assert in_view.sum() > 200  # the handle is in the image, so the check means something
    depth = scene.frame.depth[in_view]
    assert np.all((depth > 0) & (depth < handle[in_view] - 1e-3))  # nothing of it is visible


def test_pose_and_object_frame_conventions(scene):
    T = scene.T_camera_object
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    # Mug axis (+z) is the table normal; the camera looks down at the mug from above.
    up_in_camera = T[:3, 2]
    table_up = scene.T_table_camera[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(up_in_camera, table_up, atol=1e-12)
    assert up_in_camera[1] < -0.4  # image "up" is -y in the OpenCV camera frame
    p = scene.model_points
    assert p.shape == (2000, 3)
    np.testing.assert_allclose([p[:, 2].min(), p[:, 2].max()], [-MUG_HEIGHT / 2, MUG_HEIGHT / 2], atol=2e-3)
    assert p[:, 0].max() > HANDLE_CENTER_X + 0.02  # the handle sticks out along +x
    assert np.abs(p[:, 1]).max() <= MUG_RADIUS + 1e-9
    # Visible scene points, mapped into the object frame, lie on the mug surface.
    pts, _ = scene.frame.backproject(mask=scene.object_mask)
    q = pts @ invert_transform(T)[:3, :3].T + invert_transform(T)[:3, 3]
    r = np.hypot(q[:, 0], q[:, 1])
    on_wall = np.minimum(np.abs(r - MUG_RADIUS), np.abs(r - 0.0365))
    on_flat = np.minimum(np.abs(q[:, 2] - MUG_HEIGHT / 2), np.abs(q[:, 2] + MUG_HEIGHT / 2 - 0.006))
    assert np.mean(np.minimum(on_wall, on_flat) < 1e-3) > 0.99


def test_model_points_lie_on_the_mesh(scene):
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(scene.model_mesh()))
    dist = rc.compute_distance(o3d.core.Tensor(scene.model_points.astype(np.float32))).numpy()
    assert dist.max() < 1e-5


def test_deterministic_for_a_seed():
    a = make_mug_scene(rng=3, width=160, height=120, n_model_points=100)
    b = make_mug_scene(rng=3, width=160, height=120, n_model_points=100)
    c = make_mug_scene(rng=4, width=160, height=120, n_model_points=100)
    np.testing.assert_array_equal(a.frame.depth, b.frame.depth)
    np.testing.assert_array_equal(a.frame.color, b.frame.color)
    np.testing.assert_array_equal(a.model_points, b.model_points)
    np.testing.assert_array_equal(a.T_camera_object, b.T_camera_object)
    assert not np.allclose(a.T_camera_object, c.T_camera_object)
    assert a.frame.depth.shape == (120, 160)


def test_object_views_show_the_isolated_mug(scene):
    views = scene.render_object_views(n_views=3)
    assert len(views) == 3
    mesh = scene.model_mesh()
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    handle_seen = 0
    for view in views:
        assert view.mask is not None and view.mask.sum() > 3000
        # Only the mug is rendered: no depth outside the mask.
        assert not np.any(view.depth[~view.mask])
        pts, _ = view.backproject(world=True)  # world = object frame
        dist = rc.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
        assert np.quantile(dist, 0.99) < 1e-4
        handle_seen += int(np.sum(pts[:, 0] > MUG_RADIUS + 0.005))
    assert handle_seen > 100  # the views reveal the handle
    with pytest.raises(ValueError, match="n_views"):
        scene.render_object_views(n_views=0)
    for bad in (90.0, (), (30.0, float("nan"))):
        with pytest.raises(ValueError, match="elevation_deg"):
            scene.render_object_views(n_views=2, elevation_deg=bad)


def test_object_views_see_the_mugs_bottom_unless_all_from_above(scene):
    # The outer bottom (z = -height / 2) is a disc of radius MUG_RADIUS: views from below see it,
    # views from above never do (a model built from them has no bottom).
    def bottom_points(views) -> int:  # noqa: ANN001
        n = 0
        for view in views:
            pts, _ = view.backproject(world=True)
            n += int(np.sum((pts[:, 2] < pts[:, 2].min() + 0.002)
                            & (np.hypot(pts[:, 0], pts[:, 1]) < 0.5 * MUG_RADIUS)))
        return n

    assert bottom_points(scene.render_object_views(4)) > 200
    assert bottom_points(scene.render_object_views(4, elevation_deg=30.0)) == 0


def test_depth_noise_is_applied():
    clean = make_mug_scene(rng=5, width=160, height=120, n_model_points=10)
    noisy = make_mug_scene(rng=5, width=160, height=120, n_model_points=10, depth_noise=0.002)
    valid = clean.frame.depth > 0
    diff = noisy.frame.depth[valid] - clean.frame.depth[valid]
    assert 0.0015 < diff.std() < 0.0025
    np.testing.assert_array_equal(noisy.frame.depth[~valid], 0.0)


def _turned(scene, angle_deg):
    """The ground truth turned by ``angle_deg`` about the mug's own axis (object z)."""
    from scipy.spatial.transform import Rotation

    T = scene.T_camera_object.copy()
    T[:3, :3] = T[:3, :3] @ Rotation.from_rotvec([0.0, 0.0, np.radians(angle_deg)]).as_matrix()
    return T


def _handle_shows(scene, angle_deg):
    handle = _cast([mug_parts()["handle"]], scene.intrinsics, _turned(scene, angle_deg))
    seen = np.isfinite(handle)
    depth = scene.frame.depth[seen]
    return bool(np.any((depth == 0) | (handle[seen] < depth - 1e-4)))


@pytest.mark.slow
def test_hidden_handle_arc_against_independent_casts(scene):
    arc = scene.hidden_handle_arc(step=1.0)
    assert arc.success and arc.contains(0.0)
    lo, hi = arc.arc
    assert hi - lo > 60.0  # the occluder hides a wide arc; the check means something
    assert np.all(arc.violations[arc.free] == 0) and np.all(arc.violations[~arc.free] > 0)
    # Its ends, cast alone against the scene's own depth image: hidden at the ends, seen two
    # degrees beyond them (the image would change).
    for a in (lo, hi, 0.5 * (lo + hi)):
        assert not _handle_shows(scene, a), a
    for a in (lo - 2.0, hi + 2.0):
        assert _handle_shows(scene, a), a


def test_hidden_handle_arc_validation(scene):
    from dataclasses import replace

    with pytest.raises(ValueError, match="step"):
        scene.hidden_handle_arc(step=0.0)
    with pytest.raises(ValueError, match="surroundings"):
        replace(scene, surroundings={}).hidden_handle_arc()
