"""Feature backbones: FPFH(+colour), user arrays, the optional DINO backbone."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose.geometry.features import (
    ArrayBackbone,
    DinoBackbone,
    FeatureBackbone,
    FPFHBackbone,
    describe_frame,
)
from certpose.geometry.rgbd import CameraIntrinsics, RGBDFrame
from solvers.lie import make_transform


def _plane(n, rng):
    p = np.zeros((n, 3))
    p[:, :2] = rng.uniform(-0.1, 0.1, size=(n, 2))
    return p


def _sphere(n, rng, radius=0.03):
    p = rng.normal(size=(n, 3))
    return radius * p / np.linalg.norm(p, axis=1, keepdims=True)


def _sphere_normals(p):
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def test_fpfh_rows_are_unit_and_rigidly_invariant():
    rng = np.random.default_rng(0)
    p = _sphere(1500, rng)
    n = _sphere_normals(p)
    bb = FPFHBackbone(radius=0.02)
    assert isinstance(bb, FeatureBackbone)
    d = bb.describe(p, normals=n)
    assert d.shape == (1500, 33)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    T = make_transform(Rotation.from_rotvec([0.4, -1.0, 0.7]).as_matrix(), [0.3, -0.2, 1.0])
    d_moved = bb.describe(p @ T[:3, :3].T + T[:3, 3], normals=n @ T[:3, :3].T)
    np.testing.assert_allclose(d_moved, d, atol=1e-6)


def test_fpfh_similarity_separates_shapes_and_centring_helps():
    rng = np.random.default_rng(1)
    plane, sphere = _plane(2000, rng), _sphere(2000, rng, radius=0.02)
    bb = FPFHBackbone(radius=0.015, viewpoint=(0.0, 0.0, 1.0))
    hp = bb.histograms(plane)
    hs = bb.histograms(sphere, normals=_sphere_normals(sphere))
    for backbone, gap in ((bb, 0.05), (bb.fit_center(np.vstack([hp, hs])), 0.5)):
        dp, ds = backbone.finish(hp), backbone.finish(hs)
        same = min((dp @ dp.T).mean(), (ds @ ds.T).mean())
        cross = (dp @ ds.T).mean()
        assert same > cross + gap
    # Centred on the mean of both shapes, unrelated points are far from similar.
    fitted = bb.fit_center(np.vstack([hp, hs]))
    assert (fitted.finish(hp) @ fitted.finish(hs).T).mean() < 0.0
    assert (bb.finish(hp) @ bb.finish(hs).T).mean() > (fitted.finish(hp) @ fitted.finish(hs).T).mean()


def test_fpfh_colour_block():
    rng = np.random.default_rng(2)
    p = _plane(500, rng)
    red = np.tile([1.0, 0.0, 0.0], (500, 1))
    blue = np.tile([0.0, 0.0, 1.0], (500, 1))
    bb = FPFHBackbone(radius=0.02, color_weight=0.5, viewpoint=(0.0, 0.0, 1.0))
    assert bb.dim == 36
    dr, db = bb.describe(p, colors=red), bb.describe(p, colors=blue)
    np.testing.assert_allclose(np.linalg.norm(dr, axis=1), 1.0)
    np.testing.assert_allclose(dr[:, :33], db[:, :33])  # same geometry
    assert (dr * dr).sum(1).mean() > (dr * db).sum(1).mean() + 0.3
    # Without colours the colour block is zero.
    np.testing.assert_array_equal(bb.describe(p)[:, 33:], 0.0)


def test_fpfh_bad_input():
    with pytest.raises(ValueError, match="at least 5"):
        FPFHBackbone().describe(np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"Expected `points` to have shape \(N, 3\)"):
        FPFHBackbone().describe(np.zeros((10, 2)))
    bad = np.zeros((10, 3))
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        FPFHBackbone().describe(bad)
    with pytest.raises(ValueError, match="color_weight"):
        FPFHBackbone(color_weight=1.0)
    with pytest.raises(ValueError, match=r"Expected `center` to have shape \(33,\)"):
        FPFHBackbone(center=(0.0, 1.0))


def test_array_backbone():
    rng = np.random.default_rng(3)
    desc = rng.normal(size=(6, 4))
    bb = ArrayBackbone(desc)
    out = bb.describe(rng.normal(size=(6, 3)))
    np.testing.assert_allclose(out, desc / np.linalg.norm(desc, axis=1, keepdims=True))
    with pytest.raises(ValueError, match="Expected 6 points"):
        bb.describe(np.zeros((5, 3)))
    nan = desc.copy()
    nan[2, 1] = np.nan
    with pytest.raises(ValueError, match="NaN or inf values in 1 row"):
        ArrayBackbone(nan)
    with pytest.raises(ValueError, match=r"\(N, d\) or \(H, W, d\)"):
        ArrayBackbone(np.zeros(5))


def test_describe_frame_with_per_pixel_descriptors():
    cam = CameraIntrinsics(10.0, 10.0, 2.0, 1.5, 5, 4)
    depth = np.ones((4, 5))
    depth[0, 0] = 0.0
    mask = np.zeros((4, 5), bool)
    mask[:2, :] = True
    T = make_transform(Rotation.from_rotvec([0.0, 0.2, 0.0]).as_matrix(), [0.0, 1.0, 0.0])
    frame = RGBDFrame(np.zeros((4, 5, 3), np.uint8), depth, cam, T, mask)
    image = np.zeros((4, 5, 3))
    image[..., 0] = np.arange(5)[None, :] + 1.0  # depends on the column only
    image[..., 1] = 1.0
    cloud = describe_frame(frame, image)
    assert len(cloud) == 9  # 10 masked pixels, one without depth
    pts_world, px = frame.backproject(world=True)
    np.testing.assert_allclose(cloud.points, pts_world)
    expected = np.stack([px[:, 1] + 1.0, np.ones(9), np.zeros(9)], 1)
    np.testing.assert_allclose(cloud.descriptors, expected / np.linalg.norm(expected, axis=1, keepdims=True))
    with pytest.raises(ValueError, match=r"shape \(4, 5, 3\) to match the image"):
        describe_frame(frame, np.ones((4, 6, 3)))


def test_describe_frame_fpfh_on_synthetic_object_view():
    from certpose.data.synthetic import make_mug_scene

    view = make_mug_scene(rng=0, width=320, height=240, n_model_points=10).render_object_views(1)[0]
    cloud = describe_frame(view, FPFHBackbone(), voxel_size=0.005)
    assert cloud.dim == 33 and len(cloud) > 100
    np.testing.assert_allclose(np.linalg.norm(cloud.descriptors, axis=1), 1.0)
    # World frame = object frame: the points hug the mug (radius 4 cm, plus the handle).
    assert np.hypot(cloud.points[:, 0], cloud.points[:, 1]).max() < 0.07


def test_dino_backbone_needs_local_weights_and_torch(tmp_path):
    with pytest.raises(FileNotFoundError, match="dino.pt"):
        DinoBackbone(tmp_path / "dino.pt")
    weights = tmp_path / "dino.pt"
    weights.write_bytes(b"")
    try:
        import torch  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="PyTorch"):
            DinoBackbone(weights)


def test_dino_backbone_with_real_weights():
    path = os.environ.get("CERTPOSE_DINO_WEIGHTS")
    if not path or not Path(path).is_file():
        pytest.skip("set CERTPOSE_DINO_WEIGHTS to a TorchScript DINO file to run this test")
    pytest.importorskip("torch")
    bb = DinoBackbone(path)
    image = np.random.default_rng(0).integers(0, 255, size=(120, 160, 3), dtype=np.uint8)
    out = bb.describe_image(image)
    assert out.shape[:2] == (120, 160)
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, rtol=1e-5)


def test_check_descriptors_rules():
    from certpose.geometry.rgbd import check_descriptors

    ok = np.array([[0.6, 0.8], [0.0, 0.0]])
    np.testing.assert_array_equal(check_descriptors(ok, "z", 2), ok)
    with pytest.raises(ValueError, match=r"Expected `z` to have shape \(3, d\), got \(2, 2\)"):
        check_descriptors(ok, "z", 3)
    with pytest.raises(ValueError, match="at least 1 column"):
        check_descriptors(np.zeros((2, 0)), "z")
    with pytest.raises(ValueError, match=r"NaN or inf values in 1 row"):
        check_descriptors([[np.nan, 0.0], [1.0, 0.0]], "z")
    with pytest.raises(ValueError, match="L2-normalised"):
        check_descriptors([[1.0, 1.0]], "z")
    # Raw histograms and plain containers opt out of the norm (and dimension) rule.
    assert check_descriptors([[1.0, 1.0]], "h", unit_norm=False).shape == (1, 2)
    assert check_descriptors(np.zeros((2, 0)), "d", min_dim=0, unit_norm=False).shape == (2, 0)


def _open3d_fpfh(points, *, normals=None, viewpoint=(0.0, 0.0, 0.0), radius=0.025, max_nn=40,
                 normal_radius=0.0125):
    """open3d's normals (towards ``viewpoint``) and raw FPFH (N, 33), as FPFHBackbone used them."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(points)))
    if normals is None:
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=30))
        pcd.orient_normals_towards_camera_location(np.asarray(viewpoint, dtype=np.float64))
    else:
        pcd.normals = o3d.utility.Vector3dVector(np.array(normals))
    f = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    return np.asarray(pcd.normals), np.asarray(f.data).T


def _scene_voxel_points():
    """The voxel-averaged camera-frame points the scene field of YCB-Video 0002/000001 describes
    (the banana's mask box + 10 cm, and the FPFH's context around it), and which are kept."""
    from certpose.io.ycbv import load_ycbv_frame
    from certpose.model import scene as S
    from tests.conftest import require_data

    require_data("ycbv", "0002", "000001-meta.mat")
    yf = load_ycbv_frame(require_data("ycbv"), "0002/000001")
    mask = yf.object_mask("011_banana")
    p_cam, px = yf.frame.backproject(mask=False)
    lo, hi = S.bounds_from_points(p_cam[mask[px[:, 0], px[:, 1]]], margin=0.1)
    shape = tuple(int(s) for s in np.maximum(np.ceil((hi - lo) / 0.005 - 1e-9), 1).astype(int))
    grid = S.GridSpec(lo, 0.005, shape, S.VOXEL_CENTRE_OFFSET)
    v = S._frame_voxels(yf.frame, FPFHBackbone(), p_cam, p_cam, px, grid)
    return v.points, v.keep


def test_fpfh_kernels_compute_open3d_s_normals_and_fpfh():
    """The numba normals (towards the viewpoint) and FPFH are open3d's numbers: on a noisy
    synthetic surface every bit; on a real scene's voxel points every bit but for the points
    with two neighbours at exactly one distance (listed in another order: 1e-16 relative),
    and the float32 descriptors the scene stores are equal."""
    from solvers.jit import compiled

    k = compiled("certpose.geometry._fpfh_kernels")
    rng = np.random.default_rng(7)
    p = _sphere(3000, rng, radius=0.05) + rng.normal(scale=5e-4, size=(3000, 3)) + [0, 0, 0.6]
    vp = np.array([0.01, -0.02, 0.0])
    n_ref, f_ref = _open3d_fpfh(p, viewpoint=vp, radius=0.02, normal_radius=0.01)
    n = k.normals_towards(p, 0.01, 30, 0.01, vp)
    assert np.array_equal(n, n_ref)
    f = k.fpfh(p, n, 0.02, 40, 0.01, np.arange(3000, dtype=np.int64))
    assert np.array_equal(f, f_ref)
    rows = np.array([5, 0, 2999, 17], dtype=np.int64)
    assert np.array_equal(k.fpfh(p, n, 0.02, 40, 0.01, rows), f_ref[rows])

    pts, keep = _scene_voxel_points()
    n_ref, f_ref = _open3d_fpfh(pts)
    bb = FPFHBackbone()
    n = k.normals_towards(pts, 0.0125, 30, 0.0125, np.zeros(3))
    f = k.fpfh(pts, n_ref, 0.025, 40, 0.0125, np.arange(len(pts), dtype=np.int64))
    assert (n != n_ref).any(axis=1).sum() <= 5 and np.abs(n - n_ref).max() < 1e-10
    assert (f != f_ref).any(axis=1).sum() <= 5 and np.abs(f - f_ref).max() < 1e-12
    h_ref = f_ref.reshape(-1, 3, 11) / f_ref.reshape(-1, 3, 11).sum(axis=2, keepdims=True)
    d_ref = bb.finish(np.sqrt(h_ref).reshape(-1, 33)).astype(np.float32)
    assert np.array_equal(bb.describe(pts).astype(np.float32), d_ref)
    # Only the kept voxels' rows: the same rows.
    d_keep = bb.describe(pts, rows=np.flatnonzero(keep))
    assert np.array_equal(d_keep.astype(np.float32), d_ref[keep])


def test_fpfh_while_its_kernels_compile_is_open3d_s(monkeypatch):
    """A first run's scene, while the warm-up compiles the kernels, gets open3d's histograms:
    the kernels' numbers (synthetic surface: every bit; given normals; the tangent-plane
    orientation of models)."""
    import certpose.geometry.features as F

    rng = np.random.default_rng(11)
    p = _sphere(2000, rng, radius=0.05) + rng.normal(scale=5e-4, size=(2000, 3)) + [0, 0, 0.6]
    rows = np.array([3, 1999, 0])
    for bb, normals in ((FPFHBackbone(radius=0.02), None), (FPFHBackbone(radius=0.02), _sphere_normals(p)),
                        (FPFHBackbone(radius=0.02, viewpoint=None), None)):
        kernel = bb.histograms(p, normals=normals, rows=rows)
        monkeypatch.setattr("solvers.jit.pending", lambda: [F._FPFH_KERNELS])

        def not_now(*args, **kwargs):
            raise AssertionError("the kernels were called while they compile")

        monkeypatch.setattr(FPFHBackbone, "_kernel_fpfh", not_now)
        assert np.array_equal(bb.histograms(p, normals=normals, rows=rows), kernel)
        monkeypatch.undo()


def test_fpfh_given_normals_and_rows():
    rng = np.random.default_rng(3)
    p = _sphere(800, rng)
    n = _sphere_normals(p)
    bb = FPFHBackbone(radius=0.02)
    _, f_ref = _open3d_fpfh(p, normals=n, radius=0.02)
    h = f_ref.reshape(-1, 3, 11)
    h_ref = np.sqrt(h / h.sum(axis=2, keepdims=True)).reshape(-1, 33)
    assert np.array_equal(bb.histograms(p, normals=n), h_ref)
    full = bb.describe(p, normals=n, colors=rng.uniform(size=(800, 3)))
    rows = [3, 1, 799]
    np.testing.assert_array_equal(bb.describe(p, normals=n, rows=rows,
                                              colors=rng.uniform(size=(800, 3))).shape, (3, 33))
    assert np.array_equal(bb.describe(p, normals=n, rows=rows), full[rows])
    with pytest.raises(ValueError, match="rows"):
        bb.histograms(p, rows=[800])


def test_sum_by_group_equals_add_at():
    from certpose.geometry.rgbd import group_voxels, sum_by_group

    rng = np.random.default_rng(0)
    keys = rng.integers(-3, 4, size=(5000, 3))
    _, inverse, counts = group_voxels(keys)
    values = rng.normal(size=(5000, 7)) * rng.uniform(1e-3, 1e3, size=(5000, 1))
    ref = np.zeros((counts.size, 7))
    np.add.at(ref, inverse, values)
    assert np.array_equal(sum_by_group(inverse, values, counts.size), ref)
