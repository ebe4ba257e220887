"""The free-space arc about an object axis (certpose.model.arc): exact cases, the demo mug, errors."""

from __future__ import annotations

import numpy as np
import pytest

from certpose.model.arc import free_space_arc, free_space_depth
from certpose.model.grid import EMPTY, OCCUPIED, UNOBSERVED
from certpose.model.scene import SceneField


def half_space_scene(boundary: float = 0.05) -> SceneField:
    """1 cm voxels over [-0.2, 0.2]^2 x [-0.15, 0.15]; EMPTY where the voxel centre has
    x > ``boundary``, UNOBSERVED elsewhere (``boundary`` halfway between two centres)."""
    vs, shape = 0.01, (40, 40, 30)
    origin = np.array([-0.2, -0.2, -0.15])
    x = origin[0] + (np.arange(shape[0]) + 0.5) * vs
    state = np.full(shape, UNOBSERVED, dtype=np.int8)
    state[x > boundary] = EMPTY
    return SceneField(vs, origin, shape, np.zeros((*shape, 1), np.float32), state)


def test_depth_is_the_distance_to_the_free_regions_boundary() -> None:
    scene = half_space_scene()
    D = free_space_depth(scene)
    x = -0.195 + 0.01 * np.arange(40)
    # Along x, away from the grid's other faces: the centre's distance to the last non-EMPTY centre.
    np.testing.assert_allclose(D[25:33, 20, 15], x[25:33] - 0.045, atol=1e-12)
    assert np.all(D[:25] == 0)


@pytest.mark.parametrize("tolerance", [0.0, 0.005, 0.01, 0.02])
def test_arc_of_a_point_turning_into_a_half_space_of_free_space(tolerance: float) -> None:
    # A point 8 cm from the axis on the hidden side: depth into free space at angle a is
    # max(0, -0.08 cos a - 0.05), so the arc is |a| <= arccos(-(0.05 + tol) / 0.08).
    scene = half_space_scene()
    res = free_space_arc(scene, [[-0.08, 0.0, 0.0]], np.eye(4), step=0.5, tolerance=tolerance)
    assert res.success and res.status == "ok"
    end = np.degrees(np.arccos(-(0.05 + tolerance) / 0.08))
    assert res.arc[0] == pytest.approx(-end, abs=0.5) and res.arc[1] == pytest.approx(end, abs=0.5)
    assert res.arcs == (res.arc,)
    np.testing.assert_allclose(res.depth, np.maximum(-0.08 * np.cos(np.radians(res.angles)) - 0.05, 0),
                               atol=1e-9)
    assert res.contains([0.0, end - 1, 360.0]).all() and not res.contains([end + 1, 180.0]).any()


def test_reference_pose_in_free_space_and_a_run_across_the_seam() -> None:
    # The same point on the free side: the reference pose is 3 cm deep; free only for
    # |a| >= arccos((0.05 + 0.01) / 0.08) = 41.4 deg, one run across +-180 deg.
    res = free_space_arc(half_space_scene(), [[0.08, 0.0, 0.0]], np.eye(4), step=0.5, tolerance=0.01)
    assert not res.success and res.arc is None and res.status == "reference_in_free_space"
    assert "deepest 30.0 mm" in res.message and res.width == 0.0
    (lo, hi), = res.arcs
    assert lo == pytest.approx(41.5) and hi == pytest.approx(360.0 - 41.5)
    assert res.contains([180.0, -170.0, 50.0], all_arcs=True).all()
    assert not res.contains([0.0, 30.0, -30.0], all_arcs=True).any()
    assert not res.contains([180.0]).any()  # no arc through the reference


def test_axis_and_centre_in_the_object_frame_and_a_pose() -> None:
    # The pose turns the object by 90 deg about z and shifts it; the axis (object z, not unit
    # length) passes through an off-origin centre: the first case's geometry, expressed differently.
    scene = half_space_scene()
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rz, [0.02, 0.0, 0.0]
    # The object point and the axis's centre that land at scene (-0.08, 0, 0) and the origin.
    p = np.linalg.solve(Rz, np.array([-0.08, 0.0, 0.0]) - T[:3, 3])
    centre = np.linalg.solve(Rz, -T[:3, 3])
    res = free_space_arc(scene, [p], T, axis=[0.0, 0.0, 2.0], centre=centre, tolerance=0.0)
    end = np.degrees(np.arccos(-0.05 / 0.08))
    assert res.arc == pytest.approx((-end, end), abs=0.5)


def test_occupied_voxels_end_free_space_too() -> None:
    vs, shape = 0.01, (20, 20, 20)
    state = np.full(shape, EMPTY, dtype=np.int8)
    state[10, 10, 10] = OCCUPIED
    desc = np.zeros((*shape, 1), np.float32)
    desc[10, 10, 10] = 1.0
    scene = SceneField(vs, np.zeros(3), shape, desc, state)
    D = free_space_depth(scene)
    assert D[10, 10, 10] == 0 and D[10, 10, 11] == pytest.approx(0.01) and D[10, 12, 10] == pytest.approx(0.02)
    # The grid's outside is unobserved: the faces are one voxel from it.
    assert D[0, 5, 5] == pytest.approx(0.01)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"points": np.zeros((3, 2))}, r"`points` to have shape \(N, 3\)"),
        ({"points": np.zeros((0, 3))}, "`points` is empty"),
        ({"points": [[np.nan, 0, 0]]}, "NaN"),
        ({"T_scene_object": np.eye(3)}, r"`T_scene_object` to have shape \(4, 4\)"),
        ({"T_scene_object": np.diag([1.0, 1.0, -1.0, 1.0])}, "rotation"),
        ({"axis": [0.0, 0.0, 0.0]}, "`axis`"),
        ({"centre": [0.0, 0.0]}, "`centre`"),
        ({"step": 0.0}, "`step`"),
        ({"step": 30.0}, "`step`"),
        ({"tolerance": -0.001}, "`tolerance`"),
    ],
)
def test_bad_input_is_named(kwargs: dict, match: str) -> None:
    args = {"points": [[0.0, 0.0, 0.0]], "T_scene_object": np.eye(4)}
    args.update(kwargs)
    pts, T = args.pop("points"), args.pop("T_scene_object")
    with pytest.raises(ValueError, match=match):
        free_space_arc(half_space_scene(), pts, T, **args)


@pytest.mark.parametrize("seed", [pytest.param(0, marks=pytest.mark.slow), 5])
def test_demo_mug_arc_matches_the_depth_image(seed: int) -> None:
    """The demo mug's handle is hidden by construction (behind its body and the occluder box).
    The arc from the voxel grid agrees within a few degrees with the arc found directly from the
    rendered depth image: a dense surface sample of the turned mug is in free space when some
    point lies more than the scene's free-space margin (1 cm) in front of every depth within
    about 5 mm of its pixel (9 px at the demo's 0.55-0.65 m)."""
    from scipy.ndimage import minimum_filter
    from scipy.spatial.transform import Rotation

    from certpose.data.synthetic import make_mug_scene
    from certpose.estimation.pipeline import PoseParams, _scene_for
    from certpose.geometry.features import FPFHBackbone

    sc = make_mug_scene(rng=seed, n_model_points=6000)
    scene = _scene_for(sc.frame, sc.object_mask, PoseParams(), FPFHBackbone())
    res = free_space_arc(scene, sc.model_points, sc.T_camera_object, step=1.0)
    assert res.success and len(res.arcs) == 1, res.arcs
    K, T = sc.intrinsics, sc.T_camera_object
    depth = minimum_filter(sc.frame.depth, size=19, mode="constant", cval=0.0)
    free = []
    for a in res.angles:
        q = sc.model_points @ (T[:3, :3] @ Rotation.from_rotvec([0, 0, np.radians(a)]).as_matrix()).T + T[:3, 3]
        u = np.rint(K.fx * q[:, 0] / q[:, 2] + K.cx).astype(int)
        v = np.rint(K.fy * q[:, 1] / q[:, 2] + K.cy).astype(int)
        ok = (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
        d = depth[v[ok], u[ok]]
        free.append(not np.any((d > 0) & (q[ok, 2] < d - 0.01)))
    free = np.array(free)
    assert free[np.argmin(np.abs(res.angles))]
    # The image's arc: the run of free angles through 0.
    i0 = int(np.argmin(np.abs(res.angles)))
    lo = hi = 0
    while free[(i0 + hi + 1) % len(free)] and hi < len(free):
        hi += 1
    while free[(i0 - lo - 1) % len(free)] and lo < len(free):
        lo += 1
    assert res.arc[0] == pytest.approx(res.angles[i0] - lo, abs=6.0)
    assert res.arc[1] == pytest.approx(res.angles[i0] + hi, abs=6.0)
    # The handle is hidden for far more than a sliver, and not all round.
    assert 100 < res.width < 300
    # A smaller tolerance gives a sub-arc.
    tight = free_space_arc(scene, sc.model_points, sc.T_camera_object, step=1.0, tolerance=0.002)
    assert tight.success and res.arc[0] <= tight.arc[0] and tight.arc[1] <= res.arc[1]
