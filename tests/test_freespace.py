"""Free space per pixel of the depth image (certpose.model.freespace) and eq. (1)'s
``free_space="pixels"``: exact small cases, the penalty's value, validation, a real frame."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from certpose.geometry.rgbd import CameraIntrinsics, RGBDFrame
from certpose.model.arc import free_space_arc
from certpose.model.freespace import PixelFreeSpace, scene_frames
from certpose.model.grid import EMPTY, UNOBSERVED
from certpose.model.likelihood import LikelihoodParams, PoseLikelihood
from certpose.model.scene import SceneField, build_scene_field

from .conftest import require_data

K = CameraIntrinsics(100.0, 100.0, 9.5, 9.5, 20, 20)  # 20 x 20 pixels, 0.01 rad each


def wall(depth: float = 1.0, hole: tuple[int, int] | None = None) -> RGBDFrame:
    """A fronto-parallel wall ``depth`` metres away; ``hole`` = a pixel (row, col) without depth."""
    d = np.full((20, 20), depth)
    if hole is not None:
        d[hole] = 0.0
    return RGBDFrame(None, d, K)


def at_pixel(row: int, col: int, z: float) -> list[float]:
    """The camera-frame point at depth ``z`` that projects onto pixel centre (row, col)."""
    return [(col - K.cx) * z / K.fx, (row - K.cy) * z / K.fy, z]


def test_depth_in_front_behind_no_depth_outside_and_behind_the_camera() -> None:
    fs = PixelFreeSpace([wall(hole=(3, 4))], window=0)
    points = [at_pixel(10, 10, 0.7),   # 30 cm in front of the wall: free
              at_pixel(10, 10, 1.2),   # behind it: occluded
              at_pixel(3, 4, 0.5),     # a pixel without depth: unobserved
              [5.0, 0.0, 1.0],         # outside the image
              [0.0, 0.0, -0.5],        # behind the camera
              at_pixel(0, 19, 0.99)]   # a corner pixel, 1 cm in front
    np.testing.assert_allclose(fs.depth(points), [0.3, 0.0, 0.0, 0.0, 0.0, 0.01], atol=1e-12)


@pytest.mark.parametrize(("tolerance", "ramp"), [(0.0, 0.0), (0.01, 0.0), (0.01, 0.02), (0.05, 0.1)])
def test_fractions_are_the_ramp_of_the_depth(tolerance: float, ramp: float) -> None:
    # A pose that moves the points: the kernel transforms, projects and ramps exactly.
    fs = PixelFreeSpace([wall()], tolerance=tolerance, ramp=ramp, window=0)
    gaps = np.array([0.0, 0.005, 0.009, 0.011, 0.02, 0.04, 0.1, -0.03])
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.02, 0.3]
    cam = np.array([at_pixel(r, c, 1.0 - g) for r, c, g in zip(range(2, 18, 2), range(3, 19, 2), gaps,
                                                             strict=True)])
    obj = cam - T[:3, 3]
    want = (gaps > tolerance).astype(float) if ramp == 0 else np.clip((gaps - tolerance) / ramp, 0, 1)
    np.testing.assert_allclose(fs.fractions(T, obj), want, atol=1e-9)
    w = np.linspace(0.5, 2.0, gaps.size)
    T2 = np.stack([T, np.eye(4)])
    sums = fs.weighted_sum(T2, np.ascontiguousarray(obj), w)
    assert sums[0] == pytest.approx(float(w @ want))
    np.testing.assert_allclose(fs.depth(obj + T[:3, 3]), np.maximum(gaps, 0), atol=1e-12)


def test_batches_of_poses_over_several_windows_match_each_window_on_its_own() -> None:
    # More poses than one block of the kernel, two windows: the sum per pose is the mean over
    # the windows of what each window's own test charges (numpy, one window at a time).
    rng = np.random.default_rng(3)
    d = 0.8 + 0.4 * rng.random((20, 20))
    d[rng.random((20, 20)) < 0.1] = 0.0
    frame = RGBDFrame(None, d, K)
    fs = PixelFreeSpace([frame], tolerance=0.02, window=(0, 2))
    singles = [PixelFreeSpace([frame], window=w) for w in (0, 2)]
    pts = np.column_stack([rng.uniform(-0.08, 0.08, (200, 2)), rng.uniform(-0.3, 0.3, 200)])
    w = rng.uniform(0.5, 2.0, 200)
    T = np.tile(np.eye(4), (70, 1, 1))
    T[:, :3, 3] = np.column_stack([rng.normal(scale=0.02, size=(70, 2)), rng.uniform(0.6, 1.0, 70)])
    got = fs.weighted_sum(T, pts, w)
    want = [w @ np.mean([s.depth(pts + t[:3, 3]) > 0.02 for s in singles], axis=0) for t in T]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert np.ptp(got) > 1.0  # the poses differ in what they charge


@pytest.mark.parametrize("ramp", [0.0, 0.03])
def test_the_kernels_early_exits_charge_what_every_level_charges(ramp: float) -> None:
    # The kernel skips a pixel when its first level, rounded up to float32, leaves no gap, and
    # stops at the first level without a gap: the sums are those of testing every level
    # (numpy, one window at a time), ramps included, over three levels and many poses.
    rng = np.random.default_rng(5)
    d = 0.8 + 0.4 * rng.random((20, 20))
    d[rng.random((20, 20)) < 0.1] = 0.0
    frame = RGBDFrame(None, d, K)
    windows = (0, 1, 3)
    fs = PixelFreeSpace([frame], tolerance=0.01, ramp=ramp, window=windows)
    singles = [PixelFreeSpace([frame], window=w) for w in windows]
    pts = np.column_stack([rng.uniform(-0.08, 0.08, (300, 2)), rng.uniform(-0.3, 0.3, 300)])
    w = rng.uniform(0.5, 2.0, 300)
    T = np.tile(np.eye(4), (40, 1, 1))
    T[:, :3, 3] = np.column_stack([rng.normal(scale=0.02, size=(40, 2)), rng.uniform(0.6, 1.0, 40)])

    def charged(gap: np.ndarray) -> np.ndarray:
        return (gap > 0.01).astype(float) if ramp == 0 else np.clip((gap - 0.01) / ramp, 0, 1)

    want = [w @ np.mean([charged(s.depth(pts + t[:3, 3])) for s in singles], axis=0) for t in T]
    np.testing.assert_allclose(fs.weighted_sum(T, pts, w), want, rtol=1e-12, atol=1e-12)
    assert np.count_nonzero(want) > 10


def test_a_depth_float32_cannot_hold_still_charges_a_point_just_in_front_of_it() -> None:
    # 1 + 1e-9 m rounds to 1.0 in float32: a point at 1.0 m stands 1e-9 m in front of the
    # measured depth and is free (tolerance 0). A bound rounded to nearest would skip it.
    d = 1.0 + 1e-9
    assert float(np.float32(d)) < d
    fs = PixelFreeSpace([wall(d)], tolerance=0.0, window=(0, 2))
    p = np.array([at_pixel(10, 10, 1.0), at_pixel(4, 7, 1.0 + 2e-9)])
    assert p[0, 2] == 1.0
    np.testing.assert_array_equal(fs.fractions(np.eye(4), p), [1.0, 0.0])
    np.testing.assert_array_equal(fs.weighted_sum(np.eye(4)[None], p, np.ones(2)), [1.0])


def test_the_min_filter_keeps_a_silhouettes_mixed_pixels_from_counting_as_free() -> None:
    # A foreground block at 0.5 m over columns >= 10, the background at 1 m. A point at 0.8 m
    # just beside the edge (column 8) is in front of the background pixel it projects onto, but
    # within two pixels of the foreground: with window 2 it is not free, with window 0 it is.
    d = np.full((20, 20), 1.0)
    d[:, 10:] = 0.5
    d[:, 9] = 0.0  # the invalid band a real sensor leaves at the edge stays unobserved
    frame = RGBDFrame(None, d, K)
    p = [at_pixel(10, 8, 0.8), at_pixel(10, 9, 0.8), at_pixel(10, 3, 0.8)]
    np.testing.assert_allclose(PixelFreeSpace([frame], window=0).depth(p), [0.2, 0.0, 0.2], atol=1e-12)
    np.testing.assert_allclose(PixelFreeSpace([frame], window=2).depth(p), [0.0, 0.0, 0.2], atol=1e-12)


def test_several_views_free_in_any_view_is_free() -> None:
    # The second camera sits 1 m to the side at z = 1.2, looking along -x at a wall 1.5 m away.
    side = np.eye(4)
    side[:3, :3] = [[0, 0, -1], [0, 1, 0], [1, 0, 0]]
    side[:3, 3] = [1.0, 0.0, 1.2]
    fs = PixelFreeSpace([wall(), RGBDFrame(None, np.full((20, 20), 1.5), K, side)], window=0)
    # (0, 0, 0.5): 0.5 m in front of the first wall, outside the second view.
    assert fs.depth([[0.0, 0.0, 0.5]])[0] == pytest.approx(0.5)
    # (0, 0, 1.2): behind the first wall (occluded there), 0.5 m deep in the second view.
    assert fs.depth([[0.0, 0.0, 1.2]])[0] == pytest.approx(0.5)
    assert PixelFreeSpace([wall()], window=0).depth([[0.0, 0.0, 1.2]])[0] == 0.0


def box_scene(frame: RGBDFrame) -> SceneField:
    return build_scene_field(frame, np.ones((20, 20, 2)), voxel_size=0.02, margin=0.1)


class _Obj:
    """A minimal object model: points, unit descriptors, no areas."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = np.asarray(points, dtype=np.float64)
        self.descriptors = np.tile([1.0, 0.0], (self.points.shape[0], 1))


class _Cls:
    def __init__(self, scene: SceneField) -> None:
        self.log_p = np.full(scene.shape, np.log(0.9))


def test_eq1_charges_each_point_its_fraction_of_c_empty_on_top_of_the_voxel_term() -> None:
    frame = wall()
    scene = box_scene(frame)
    assert (scene.state == EMPTY).any() and scene.frames == (frame,)
    pts = np.array([at_pixel(r, c, z) for r, c, z in [(10, 10, 0.95), (5, 7, 0.985), (12, 3, 0.998),
                                                      (8, 8, 1.0), (15, 15, 1.1)]])
    params = LikelihoodParams(free_space="pixels", depth_tolerance=0.004, depth_ramp=0.01,
                              depth_window=0, c_empty=-12.0)
    lik = PoseLikelihood(scene, _Cls(scene), _Obj(pts), params=params)
    # The voxel part: the same scene with its EMPTY voxels unobserved.
    state = np.where(scene.state == EMPTY, UNOBSERVED, scene.state).astype(np.int8)
    bare = SceneField(scene.voxel_size, scene.origin, scene.shape, scene.descriptors, state)
    voxel = PoseLikelihood(bare, _Cls(bare), _Obj(pts), params=LikelihoodParams(c_empty=-12.0))
    T = np.eye(4)
    frac = np.clip((np.array([0.05, 0.015, 0.002, 0.0, 0.0]) - 0.004) / 0.01, 0, 1)
    want = voxel.point_terms(T) + frac * (-12.0 - np.log(0.1))
    np.testing.assert_allclose(lik.point_terms(T), want, atol=1e-9)
    # The batch (threaded above 16 poses) sums the same terms.
    shifts = np.tile(np.eye(4), (40, 1, 1))
    shifts[:, 2, 3] = np.linspace(-0.02, 0.02, 40)
    batch = lik.log_likelihood(shifts)
    np.testing.assert_allclose(batch, [lik.point_terms(S).sum() for S in shifts], atol=1e-9)
    assert np.ptp(batch - voxel.log_likelihood(shifts)) > 1.0  # the charge moves with the pose
    # with_object and other params recompute the test.
    other = lik.with_object(_Obj(pts), params=replace(params, depth_tolerance=0.1))
    np.testing.assert_allclose(other.point_terms(T), voxel.point_terms(T), atol=1e-9)


def test_pixels_need_a_scene_that_keeps_its_depth_images() -> None:
    scene = box_scene(wall())
    bare = SceneField(scene.voxel_size, scene.origin, scene.shape, scene.descriptors, scene.state)
    with pytest.raises(ValueError, match="keeps no depth image"):
        PoseLikelihood(bare, _Cls(bare), _Obj([[0, 0, 0.9]]), params=LikelihoodParams(free_space="pixels"))
    with pytest.raises(ValueError, match="keeps no depth image"):
        free_space_arc(bare, [[0.0, 0.0, 0.0]], np.eye(4), free_space="pixels")
    with pytest.raises(ValueError, match="keeps no depth image"):
        scene_frames(bare)
    with pytest.raises(TypeError, match=r"`frames\[0\]` must be an RGBDFrame"):
        SceneField(scene.voxel_size, scene.origin, scene.shape, scene.descriptors, scene.state,
                   frames=(np.zeros((20, 20)),))


def test_save_and_load_keep_the_depth_images(tmp_path) -> None:  # noqa: ANN001
    frame = wall(hole=(2, 2))
    scene = box_scene(frame)
    scene.save(tmp_path / "s.npz")
    back = SceneField.load(tmp_path / "s.npz")
    (f,) = back.frames
    np.testing.assert_array_equal(f.depth, frame.depth)
    assert f.intrinsics == frame.intrinsics and f.color is None
    np.testing.assert_array_equal(f.T_world_camera, frame.T_world_camera)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"free_space": "grid"}, "`free_space` must be 'voxels', 'pixels' or 'auto'"),
    ({"free_space": "pixels", "free_space_tolerance": 0.01}, "with free_space='pixels' use"),
    ({"free_space": "pixels", "free_space_from": "surface"}, "with free_space='pixels' use"),
    ({"free_space": "pixels", "free_space_ramp": 0.0}, "with free_space='pixels' use"),
    ({"depth_tolerance": -0.01}, "`depth_tolerance` must be >= 0"),
    ({"depth_ramp": float("nan")}, "`depth_ramp` must be finite"),
    ({"depth_window": 1.5}, "`depth_window` must be a non-negative integer"),
    ({"depth_window": -1}, "`depth_window` must be a non-negative integer"),
])
def test_option_validation(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        LikelihoodParams(**kwargs)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"tolerance": -1.0}, "`tolerance` must be a non-negative"),
    ({"ramp": np.inf}, "`ramp` must be a non-negative"),
    ({"window": 2.5}, "`window` must be a non-negative integer"),
])
def test_pixel_free_space_validation(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        PixelFreeSpace([wall()], **kwargs)
    with pytest.raises(ValueError, match="`frames` is empty"):
        PixelFreeSpace([])


@pytest.mark.parametrize("tolerance", [0.0, 0.01, 0.02])
def test_arc_of_a_point_turning_towards_the_camera(tolerance: float) -> None:
    # A point 8 cm from an axis parallel to the image's y axis through (0, 0, 1.05): at angle a it
    # stands at z = 1.05 - 0.08 sin a, i.e. max(0, 0.08 sin a - 0.05) in front of the wall at 1 m.
    T = np.eye(4)
    T[2, 3] = 1.05
    big = CameraIntrinsics(100.0, 100.0, 99.5, 99.5, 200, 200)
    scene = build_scene_field(RGBDFrame(None, np.full((200, 200), 1.0), big), np.ones((200, 200, 2)),
                              voxel_size=0.02)
    res = free_space_arc(scene, [[0.08, 0.0, 0.0]], T, axis=(0, 1, 0), free_space="pixels",
                         tolerance=tolerance, window=0, baseline="none", max_violations=0)
    a = np.radians(res.angles)
    # Rotation about +y by a sends (0.08, 0, 0) to (0.08 cos a, 0, -0.08 sin a).
    np.testing.assert_allclose(res.depth, np.maximum(0.08 * np.sin(a) - 0.05, 0), atol=1e-9)
    end = np.degrees(np.arcsin((0.05 + tolerance) / 0.08))
    assert res.success
    lo, hi = res.arc
    # The free run wraps around: from 180 - end to 360 + end.
    assert hi - lo == pytest.approx(360.0 - (180.0 - 2 * end), abs=1.0)


def test_pixel_arc_counts_points_beyond_the_reference_poses_own() -> None:
    # The object's origin 5 cm in front of a wall at 1 m, turning about its y axis: a point on the
    # axis stands 5 cm deep in free space at every angle (as an annotated pose's silhouette
    # points stand past the observed silhouette), one 10 cm behind the origin stands
    # 0.05 - 0.1 cos a in front of the wall (free while cos a >= 0.4 at a 1-cm tolerance).
    # Against no baseline nothing is free; against the reference pose's own count the arc is
    # the turning point's.
    T = np.eye(4)
    T[2, 3] = 0.95
    big = CameraIntrinsics(100.0, 100.0, 99.5, 99.5, 200, 200)
    scene = build_scene_field(RGBDFrame(None, np.full((200, 200), 1.0), big), np.ones((200, 200, 2)),
                              voxel_size=0.02)
    pts = [[0.0, 0.0, 0.1], [0.0, 0.01, 0.0]]
    none = free_space_arc(scene, pts, T, axis=(0, 1, 0), window=0, baseline="none", max_violations=0)
    assert not none.success and not none.free.any()
    ref = free_space_arc(scene, pts, T, axis=(0, 1, 0), window=0, max_violations=0)
    alone = free_space_arc(scene, pts[:1], T, axis=(0, 1, 0), window=0, baseline="none", max_violations=0)
    assert ref.success and ref.arc == alone.arc
    end = np.degrees(np.arccos(0.4))
    assert ref.arc[0] == pytest.approx(-end, abs=0.5) and ref.arc[1] == pytest.approx(end, abs=0.5)
    assert "baseline: 1 points" in ref.message
    with pytest.raises(ValueError, match="baseline"):
        free_space_arc(scene, pts, T, baseline="truth")


@pytest.mark.slow
def test_real_frame_charges_the_turned_mugs_handle() -> None:
    from scipy.spatial.transform import Rotation

    from certpose.io.ycbv import load_model_points, load_ycbv_frame

    root = require_data("ycbv")
    yf = load_ycbv_frame(root, "0000/000001")
    mask = yf.object_mask("025_mug")
    scene = build_scene_field(yf.frame, np.zeros((*yf.frame.shape, 1)), voxel_size=0.005,
                              roi_mask=mask)
    pts = load_model_points(root / "models" / "025_mug" / "points.xyz")
    G = yf.poses["025_mug"]
    fs = PixelFreeSpace.from_scene(scene, tolerance=0.01, window=15)
    handle = pts[:, 0] >= 0.045

    def charged(angle: float) -> np.ndarray:
        T = G.copy()
        T[:3, :3] = G[:3, :3] @ Rotation.from_rotvec([0, 0, np.radians(angle)]).as_matrix()
        return fs.fractions(T, pts)

    # At the truth (handle hidden behind the body) at most a few rim points are charged; turned
    # by -60 deg the handle swings out beside the mug into observed free space.
    assert charged(0.0).sum() <= 5
    turned = charged(-60.0)
    assert turned[handle].sum() >= 20 and turned[handle].sum() > 0.5 * turned.sum()


def test_auto_reads_pixels_when_the_scene_keeps_its_depth_images() -> None:
    scene = box_scene(wall())
    bare = SceneField(scene.voxel_size, scene.origin, scene.shape, scene.descriptors, scene.state)
    pts = np.array([at_pixel(10, 10, 0.95), at_pixel(5, 7, 0.9)])
    T = np.eye(4)

    def terms(s: SceneField, **kw: object) -> np.ndarray:
        return PoseLikelihood(s, _Cls(s), _Obj(pts), params=LikelihoodParams(**kw)).point_terms(T)

    np.testing.assert_array_equal(terms(scene, free_space="auto"), terms(scene, free_space="pixels"))
    np.testing.assert_array_equal(terms(scene), terms(scene, free_space="pixels"))  # the default
    np.testing.assert_array_equal(terms(bare, free_space="auto"), terms(bare, free_space="voxels"))
    # Voxel grading options ask for voxels.
    graded = {"free_space_tolerance": 0.01}
    np.testing.assert_array_equal(terms(scene, free_space="auto", **graded),
                                  terms(scene, free_space="voxels", **graded))
    assert not np.array_equal(terms(scene, free_space="pixels"), terms(scene, free_space="voxels"))
