"""The scene field: free/unobserved labelling, fusion, trilinear interpolation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from certpose.geometry.features import ArrayBackbone, FPFHBackbone
from certpose.geometry.rgbd import CameraIntrinsics, RGBDFrame
from certpose.model.grid import EMPTY, OCCUPIED, UNOBSERVED
from certpose.model.scene import SceneField, build_scene_field
from solvers.lie import make_transform
from tests.conftest import require_data

# A 64x48 camera looking at a wall at z = 1 m: the wall spans |x| < 0.7875, |y| < 0.5875.
CAM = CameraIntrinsics(fx=40.0, fy=40.0, cx=31.5, cy=23.5, width=64, height=48)
BOUNDS = (np.array([-1.2, -0.9, 0.05]), np.array([1.2, 0.9, 1.55]))
VOXEL = 0.1


def _wall_frame(T_world_camera=None):
    depth = np.ones((48, 64))
    color = np.full((48, 64, 3), 100, np.uint8)
    return RGBDFrame(color, depth, CAM, np.eye(4) if T_world_camera is None else T_world_camera)


def _left_right_descriptors():
    desc = np.zeros((48, 64, 2))
    desc[:, :32, 0] = 1.0  # left half of the image (x < 0)
    desc[:, 32:, 1] = 1.0
    return desc


def _centres(scene):
    ijk = np.stack(np.unravel_index(np.arange(scene.n_voxels), scene.shape), axis=1)
    return scene.grid_to_world(ijk)


def test_flat_wall_free_occupied_unobserved():
    scene = build_scene_field(
        _wall_frame(), _left_right_descriptors(), voxel_size=VOXEL, bounds=BOUNDS, free_space_margin=0.15
    )
    assert scene.shape == (24, 18, 15)
    c = _centres(scene)
    state = scene.state.reshape(-1)
    x, y, z = np.abs(c[:, 0]) / c[:, 2], np.abs(c[:, 1]) / c[:, 2], c[:, 2]
    # Clearly inside the frustum and in front of the wall by more than the margin: EMPTY.
    front = (x < 0.7) & (y < 0.5) & (z <= 0.8)
    assert front.sum() > 100
    assert np.all(state[front] == EMPTY)
    # Clearly outside the frustum, or behind the wall: UNOBSERVED.
    outside = (x > 0.9) | (y > 0.7)
    behind = z >= 1.1
    assert outside.sum() > 100 and behind.sum() > 100
    assert np.all(state[outside] == UNOBSERVED)
    assert np.all(state[behind] == UNOBSERVED)
    # Within the margin in front of the wall: not carved.
    assert np.all(state[np.isclose(z, 0.9)] != EMPTY)
    # The wall layer: voxels intersecting |x| < 0.7875, |y| < 0.5875 -> 16 x 12 occupied.
    assert scene.counts()["occupied"] == 16 * 12
    occ = scene.occupied_centers()
    np.testing.assert_allclose(occ[:, 2], 1.0)
    assert np.abs(occ[:, 0]).max() < 0.8 and np.abs(occ[:, 1]).max() < 0.6
    # Descriptors are the means of the per-pixel descriptors: left half [1, 0], right [0, 1].
    desc = scene.occupied_descriptors()
    left = occ[:, 0] < 0
    np.testing.assert_allclose(desc[left], [[1.0, 0.0]] * int(left.sum()), atol=1e-6)
    np.testing.assert_allclose(desc[~left], [[0.0, 1.0]] * int((~left).sum()), atol=1e-6)
    # Only occupied voxels carry descriptors.
    assert not np.any(scene.descriptors[scene.state != OCCUPIED])


def test_two_frames_fuse_free_space_and_surfaces():
    frame1 = _wall_frame()
    frame2 = _wall_frame(make_transform(np.eye(3), [0.4, 0.0, 0.0]))
    kwargs = dict(voxel_size=VOXEL, bounds=BOUNDS, free_space_margin=0.15)
    one = build_scene_field(frame1, _left_right_descriptors(), **kwargs)
    both = build_scene_field([frame1, frame2], [_left_right_descriptors()] * 2, **kwargs)
    probe = np.array([[0.75, 0.0, 0.7]])  # outside frame 1's frustum, inside frame 2's
    assert one.state_at(probe)[0] == UNOBSERVED
    assert both.state_at(probe)[0] == EMPTY
    # Frame 2 sees the wall up to x = 0.4 + 0.7875: 4 more voxel columns.
    assert both.counts()["occupied"] == (16 + 4) * 12
    assert both.counts()["empty"] > one.counts()["empty"]


def test_world_frame_follows_first_camera_pose():
    T = make_transform(np.eye(3), [0.0, 0.0, 0.3])
    scene = build_scene_field(
        _wall_frame(T), _left_right_descriptors(), voxel_size=VOXEL, bounds=BOUNDS, free_space_margin=0.15
    )
    np.testing.assert_allclose(scene.occupied_centers()[:, 2], 1.3)


def test_default_bounds_and_roi_mask():
    roi = np.zeros((48, 64), bool)
    roi[20:28, 28:36] = True
    scene = build_scene_field(_wall_frame(), _left_right_descriptors(), voxel_size=0.02, roi_mask=roi, margin=0.05)
    lo, hi = scene.bounds
    pts, _ = _wall_frame().backproject(mask=roi)
    assert np.all(lo <= pts.min(axis=0) - 0.05 + 1e-9)
    assert np.all(hi >= pts.max(axis=0) + 0.05 - 1e-9)
    assert np.all(hi - lo < pts.max(axis=0) - pts.min(axis=0) + 0.1 + 0.02 + 1e-9)


def _linear_field(dtype=np.float64):
    shape = (4, 5, 6)
    origin = np.array([0.3, -0.2, 0.1])
    vs = 0.1
    A = np.array([[1.0, -2.0, 0.5], [0.3, 0.7, -1.1]])
    b = np.array([0.2, -0.4])
    ijk = np.stack(np.unravel_index(np.arange(np.prod(shape)), shape), axis=1)
    centres = origin + (ijk + 0.5) * vs
    desc = (centres @ A.T + b).reshape(*shape, 2).astype(dtype)
    state = np.full(shape, OCCUPIED, np.int8)
    return SceneField(vs, origin, shape, desc, state), A, b


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-12), (np.float32, 1e-5)])
def test_trilinear_interpolation_exact_on_linear_fields(dtype, tol):
    scene, A, b = _linear_field(dtype)
    rng = np.random.default_rng(3)
    g = rng.uniform(0.0, 1.0, size=(200, 3)) * (np.asarray(scene.shape) - 1)
    pts = scene.grid_to_world(g)
    np.testing.assert_allclose(scene.interpolate(pts), pts @ A.T + b, atol=tol)
    flat, w = scene.trilinear_weights(pts)
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    assert flat.max() < scene.n_voxels


def test_interpolation_treats_non_occupied_corners_as_null():
    shape = (4, 4, 4)
    desc = np.zeros((*shape, 3))
    desc[1, 1, 1] = [0.0, 0.6, 0.8]
    state = np.full(shape, EMPTY, np.int8)
    state[1, 1, 1] = OCCUPIED
    scene = SceneField(0.01, np.zeros(3), shape, desc, state)
    at = scene.grid_to_world(np.array([[1.0, 1.0, 1.0], [1.5, 1.0, 1.0], [2.0, 1.0, 1.0], [1.25, 1.5, 0.5]]))
    np.testing.assert_allclose(
        scene.interpolate(at),
        [[0.0, 0.6, 0.8], [0.0, 0.3, 0.4], [0.0, 0.0, 0.0], np.multiply([0.0, 0.6, 0.8], 0.75 * 0.5 * 0.5)],
        atol=1e-12,
    )
    # Outside the grid: zero descriptor, UNOBSERVED state, padded index.
    far = np.array([[1.0, 1.0, 1.0]])
    np.testing.assert_array_equal(scene.interpolate(far), [[0.0, 0.0, 0.0]])
    assert scene.state_at(far)[0] == UNOBSERVED
    flat, w = scene.trilinear_weights(far)
    assert np.all(flat == scene.n_voxels) and np.all(w == 0)
    # Half a voxel outside the first centre: only the inside corners count.
    edge = scene.grid_to_world(np.array([[-0.5, 1.0, 1.0]]))
    _, w = scene.trilinear_weights(edge)
    np.testing.assert_allclose(w.sum(), 0.5)


def test_state_at_and_occupied_accessors():
    scene, _, _ = _linear_field()
    state = np.array(scene.state)
    state[0, 0, 0] = EMPTY
    state[3, 4, 5] = UNOBSERVED
    desc = np.array(scene.descriptors)
    desc[state != OCCUPIED] = 0.0
    scene = SceneField(scene.voxel_size, scene.origin, scene.shape, desc, state)
    centres = _centres(scene)
    np.testing.assert_array_equal(scene.state_at(centres), state.reshape(-1))
    # Nearest voxel: a point anywhere inside a voxel gets its state.
    np.testing.assert_array_equal(scene.state_at(centres + 0.049), state.reshape(-1))
    occ = scene.occupied_index()
    assert occ.size == scene.n_voxels - 2
    np.testing.assert_allclose(scene.occupied_centers(), centres[occ])
    np.testing.assert_allclose(scene.occupied_descriptors(), desc.reshape(-1, 2)[occ])
    lookup = scene.occupied_lookup()
    assert lookup[0] == -1 and lookup[-1] == -1
    np.testing.assert_array_equal(lookup[occ], np.arange(occ.size))
    np.testing.assert_allclose(scene.world_to_grid(scene.grid_to_world(np.array([[1.2, 3.4, 0.5]]))), [[1.2, 3.4, 0.5]])


def test_scene_field_validation():
    shape = (2, 2, 2)
    state = np.full(shape, EMPTY, np.int8)
    with pytest.raises(ValueError, match="zero at voxels that are not OCCUPIED"):
        SceneField(0.1, np.zeros(3), shape, np.ones((*shape, 2)), state)
    with pytest.raises(ValueError, match=r"Expected `state` to have shape \(2, 2, 2\)"):
        SceneField(0.1, np.zeros(3), shape, np.zeros((*shape, 2)), np.zeros((2, 2), np.int8))
    with pytest.raises(ValueError, match="`state` holds values"):
        SceneField(0.1, np.zeros(3), shape, np.zeros((*shape, 2)), np.full(shape, 7))
    bad = np.zeros((*shape, 2))
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        SceneField(0.1, np.zeros(3), shape, bad, np.full(shape, OCCUPIED))
    with pytest.raises(ValueError, match="voxel_size"):
        SceneField(0.0, np.zeros(3), shape, np.zeros((*shape, 2)), state)


def test_build_bad_input():
    frame = _wall_frame()
    nan_desc = _left_right_descriptors()
    nan_desc[3, 4, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        build_scene_field(frame, nan_desc, voxel_size=VOXEL, bounds=BOUNDS)
    with pytest.raises(ValueError, match="`roi_mask\\[0\\]` is empty"):
        build_scene_field(frame, _left_right_descriptors(), roi_mask=np.zeros((48, 64), bool))
    with pytest.raises(ValueError, match="max_voxels"):
        build_scene_field(frame, _left_right_descriptors(), voxel_size=0.001, bounds=BOUNDS)
    with pytest.raises(ValueError, match="too coarse"):  # e.g. centimetres given as metres
        build_scene_field(frame, _left_right_descriptors(), voxel_size=10.0, bounds=BOUNDS)
    with pytest.raises(ValueError, match="max must exceed min"):
        build_scene_field(frame, _left_right_descriptors(), bounds=(np.ones(3), np.zeros(3)))
    with pytest.raises(ValueError, match=r"shape \(48, 64, 2\) to match the image, got \(48, 63, 2\)"):
        build_scene_field(frame, np.ones((48, 63, 2)), voxel_size=VOXEL, bounds=BOUNDS)
    with pytest.raises(ValueError, match="`frames` is empty"):
        build_scene_field([], None)
    with pytest.raises(ValueError, match="No observed point"):
        build_scene_field(frame, _left_right_descriptors(), voxel_size=VOXEL, bounds=(np.full(3, 5.0), np.full(3, 6.0)))


def test_fpfh_scene_on_synthetic_mug():
    from certpose.data.synthetic import make_mug_scene

    syn = make_mug_scene(rng=1)
    scene = build_scene_field(syn.frame, voxel_size=0.005, roi_mask=syn.object_mask, margin=0.04)
    assert scene.dim == 33 and isinstance(scene.backbone, FPFHBackbone)
    assert scene.backbone.center is None
    norms = np.linalg.norm(scene.occupied_descriptors(), axis=1)
    np.testing.assert_allclose(norms[norms > 0], 1.0, rtol=1e-5)
    # Scene normals always face the camera, whatever the backbone's viewpoint setting.
    other = build_scene_field(
        syn.frame, FPFHBackbone(viewpoint=None), voxel_size=0.005, roi_mask=syn.object_mask, margin=0.04
    )
    np.testing.assert_allclose(other.descriptors, scene.descriptors, atol=1e-6)
    fitted = build_scene_field(
        syn.frame, FPFHBackbone(), voxel_size=0.005, roi_mask=syn.object_mask, margin=0.04, fit_backbone=True
    )
    assert fitted.backbone.center is not None
    np.testing.assert_array_equal(fitted.state, scene.state)
    # Centred on the scene mean: the average descriptor is small (unrelated pairs ~ 0).
    mean = fitted.occupied_descriptors().mean(axis=0)
    assert mean @ mean < 0.1
    assert scene.occupied_descriptors().mean(axis=0) @ scene.occupied_descriptors().mean(axis=0) > 0.3


def _ycbv_root() -> Path:
    require_data("ycbv", "0000", "000001-meta.mat")
    return require_data("ycbv")


def test_real_frame_ground_truth_respects_free_space():
    from certpose.io.ycbv import load_model_points, load_ycbv_frame

    root = _ycbv_root()
    data = load_ycbv_frame(root, "0000/000001")
    mask = data.object_mask("025_mug")
    scene = build_scene_field(data.frame, voxel_size=0.005, roi_mask=mask, margin=0.05)
    model = load_model_points(root / "models" / "025_mug" / "points.xyz")
    T = data.poses["025_mug"]
    q = model @ T[:3, :3].T + T[:3, 3]
    state = scene.state_at(q)
    # The true pose puts almost no model point in observed free space, and many on surfaces.
    assert np.mean(state == EMPTY) < 0.03
    assert np.mean(state == OCCUPIED) > 0.2
    # A pose 3 cm towards the camera violates free space massively.
    shifted = q - 0.03 * T[:3, 3] / np.linalg.norm(T[:3, 3])
    assert np.mean(scene.state_at(shifted) == EMPTY) > 0.3


def test_array_backbone_rejects_nan():
    bad = np.ones((5, 3))
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ArrayBackbone(bad)


@pytest.mark.parametrize("fit", [False, True])
def test_a_frame_that_misses_the_grid_adds_nothing(fit):
    far = _wall_frame(make_transform(np.eye(3), [0.0, 0.0, 5.0]))  # its wall is at z = 6
    kwargs = dict(voxel_size=VOXEL, bounds=BOUNDS, free_space_margin=0.15, fit_backbone=fit)
    backbone = FPFHBackbone(radius=0.25)
    one = build_scene_field(_wall_frame(), backbone, **kwargs)
    both = build_scene_field([_wall_frame(), far], backbone, **kwargs)
    np.testing.assert_array_equal(both.state, one.state)
    np.testing.assert_allclose(both.descriptors, one.descriptors, atol=1e-6)
    assert one.counts()["occupied"] == 16 * 12


def test_save_and_load_round_trip(tmp_path):
    scene = build_scene_field(
        _wall_frame(), FPFHBackbone(radius=0.25), voxel_size=VOXEL, bounds=BOUNDS, fit_backbone=True
    )
    path = tmp_path / "scene.npz"
    scene.save(path)
    back = SceneField.load(path)
    np.testing.assert_array_equal(back.state, scene.state)
    np.testing.assert_array_equal(back.descriptors, scene.descriptors)
    np.testing.assert_array_equal(back.origin, scene.origin)
    assert back.voxel_size == scene.voxel_size and back.shape == scene.shape
    assert back.backbone == scene.backbone  # fitted centre included
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        SceneField.load(tmp_path / "missing.npz")
    (tmp_path / "bad.npz").write_bytes(b"garbage")
    with pytest.raises(ValueError, match="bad.npz"):
        SceneField.load(tmp_path / "bad.npz")
    np.save(tmp_path / "state.npy", scene.state)  # np.load gives a bare array: no TypeError
    (tmp_path / "cut.npz").write_bytes(path.read_bytes()[:400])  # no BadZipFile
    for name in ("state.npy", "cut.npz"):
        with pytest.raises(ValueError, match=f"{name}: not a .npz archive"):
            SceneField.load(tmp_path / name)


def test_grid_spec_is_the_scene_geometry():
    from certpose.model.grid import GridSpec

    g = GridSpec(np.array([1.0, -2.0, 0.5]), 0.25, (4, 3, 2), 0.5)
    ijk = np.array([[0, 0, 0], [3, 2, 1]])
    c = g.centres(ijk)
    np.testing.assert_allclose(c, [[1.125, -1.875, 0.625], [1.875, -1.375, 0.875]])
    np.testing.assert_allclose(g.to_grid(c), ijk, atol=1e-12)
    np.testing.assert_array_equal(g.voxel_of(c), ijk)
    # A voxel's lower faces belong to it, its upper faces to the next one.
    np.testing.assert_array_equal(g.voxel_of(g.origin[None] + 0.25), [[1, 1, 1]])
    assert g.inside(np.array([[3, 2, 1], [4, 0, 0], [0, -1, 0]])).tolist() == [True, False, False]
    assert [a.shape for a in g.axes()] == [(4,), (3,), (2,)]
    np.testing.assert_allclose(g.axes()[0], g.centres(np.c_[np.arange(4), np.zeros((4, 2))])[:, 0])
