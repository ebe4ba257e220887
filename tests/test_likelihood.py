"""Eq. (1): the batched numba likelihood against a slow reference loop, and input checks."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose.geometry.objects import ObjectModel
from certpose.model.classifier import ClassifierStatus, ObjectClassification
from certpose.model.grid import EMPTY, OCCUPIED, UNOBSERVED
from certpose.model.likelihood import (
    LikelihoodParams,
    PoseLikelihood,
    free_space_values,
    log_likelihood,
)
from certpose.model.scene import SceneField
from solvers.lie import make_transform


def _unit_rows(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    x = rng.normal(size=(n, d))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _world(seed: int = 0, shape: tuple[int, int, int] = (12, 10, 9), d: int = 7, *,
           p_states=(0.3, 0.3, 0.4), voxel: float = 0.01, origin=(-0.06, -0.05, 0.2),
           n_points: int = 60, spread: float = 0.03):
    """A random hand-built scene, classifier and object (states mixed everywhere by default;
    ``p_states``: the chances of UNOBSERVED, EMPTY, OCCUPIED)."""
    rng = np.random.default_rng(seed)
    state = rng.choice([UNOBSERVED, EMPTY, OCCUPIED], size=shape, p=list(p_states)).astype(np.int8)
    desc = np.zeros((*shape, d))
    occ = state == OCCUPIED
    desc[occ] = _unit_rows(rng, int(occ.sum()), d)
    scene = SceneField(voxel, np.array(origin, dtype=np.float64), shape, desc, state)
    log_p = np.where(rng.random(shape) < 0.5, math.log(0.9), -5.0)
    cls = ObjectClassification(log_p, occ & (log_p > -1), -5.0, "test", ClassifierStatus.OK, "")
    obj = ObjectModel(rng.normal(scale=spread, size=(n_points, 3)), _unit_rows(rng, n_points, d))
    return rng, scene, cls, obj


def _reference(scene, cls, obj, T, params: LikelihoodParams, spread: dict | None = None,
               descriptors: dict | None = None) -> float:
    """Eq. (1) point by point, corner by corner, in plain Python (free-space values per voxel
    from :func:`free_space_values`, tested on its own below).

    ``spread``: per-voxel classifier terms relative to unobserved space (by voxel index, absent:
    0), added at every corner in place of the occupied voxels' own ``cls.log_p`` (the
    ``field_blur`` option, tests/test_field_blur.py).

    ``descriptors``: per-voxel scene descriptors (by voxel index, absent: 0) at every corner, in
    place of the occupied voxels' own (the ``descriptor_blur`` option,
    tests/test_descriptor_blur.py).

    With ``free_space_at="point"``: EMPTY corners count as unobserved, and the point pays the
    ramp of its depth, the trilinear blend of scipy's full distance transform (uncapped) minus
    half a voxel."""
    at_point = params.free_space_at == "point"
    background = free_space_values(scene.state, scene.voxel_size, params)
    if at_point:
        D = _edt_depth(scene.state, scene.voxel_size, params)
    total = 0.0
    for p, z in zip(obj.points, obj.descriptors, strict=True):
        q = T[:3, :3] @ p + T[:3, 3]
        g = (q - scene.origin) / scene.voxel_size - 0.5  # voxel centres at integers
        i0 = np.floor(g).astype(int)
        if np.any(i0 < -1) or np.any(i0 > np.asarray(scene.shape) - 1):
            total += params.log_p_unobserved  # beyond the padded grid: unobserved
            continue
        f = g - i0
        term = 0.0
        depth = 0.0
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    w = ((f[0] if dx else 1 - f[0]) * (f[1] if dy else 1 - f[1])
                         * (f[2] if dz else 1 - f[2]))
                    ijk = i0 + (dx, dy, dz)
                    inside = all(0 <= ijk[a] < scene.shape[a] for a in range(3))
                    s = scene.state[tuple(ijk)] if inside else UNOBSERVED
                    sim = 0.0
                    if descriptors is not None and tuple(ijk) in descriptors:
                        sim = params.beta * float(descriptors[tuple(ijk)] @ z)
                    if s == OCCUPIED:
                        own = cls.log_p[tuple(ijk)] if spread is None else params.log_p_unobserved
                        v = own + (params.beta * float(scene.descriptors[tuple(ijk)] @ z)
                                   if descriptors is None else 0.0)
                    elif s == EMPTY:
                        v = background[tuple(ijk)]
                        if at_point:
                            depth += w * D[tuple(ijk)]
                    else:
                        v = params.log_p_unobserved
                    term += w * (v + sim + (0.0 if spread is None else spread.get(tuple(ijk), 0.0)))
        if at_point:
            over = depth - 0.5 * scene.voxel_size - params.free_space_tolerance
            ramp = params.free_space_ramp
            frac = float(over > 0) if ramp == 0 else min(max(over / ramp, 0.0), 1.0)
            term += frac * (params.c_empty - params.log_p_unobserved)
        total += term
    return total


def _edt_depth(state, voxel_size, params):
    """Distance from each EMPTY voxel centre to the nearest voxel centre that is not EMPTY
    (``free_space_from="boundary"``, outside the grid unobserved) or occupied (``"surface"``),
    0 elsewhere: scipy's full transform, uncapped (no erosion)."""
    from scipy.ndimage import distance_transform_edt

    empty = state == EMPTY
    if params.free_space_from == "boundary":
        d = distance_transform_edt(np.pad(empty, 1), sampling=voxel_size)[1:-1, 1:-1, 1:-1]
    else:
        d = distance_transform_edt(state != OCCUPIED, sampling=voxel_size)
    return np.where(empty, d, 0.0)


def _random_poses(rng, n, centre, spread):
    return np.stack([make_transform(Rotation.random(random_state=rng).as_matrix(), centre + rng.uniform(-spread, spread, 3))
                     for _ in range(n)])


def test_batch_equals_slow_reference_loop():
    rng, scene, cls, obj = _world(0)
    params = LikelihoodParams(beta=1.7, c_empty=-8.0, log_p_unobserved=math.log(0.2))
    lik = PoseLikelihood(scene, cls, obj, params=params)
    centre = scene.origin + np.asarray(scene.shape) * scene.voxel_size / 2
    # 40 poses, partly outside the grid.
    poses = _random_poses(rng, 40, centre, 0.06)
    fast = lik(poses)
    slow = np.array([_reference(scene, cls, obj, T, params) for T in poses])
    np.testing.assert_allclose(fast, slow, rtol=1e-5, atol=1e-4)
    # The single-thread path and the single-pose call agree too.
    np.testing.assert_allclose(lik(poses[:3]), slow[:3], rtol=1e-5, atol=1e-4)
    assert lik(poses[5]) == pytest.approx(slow[5], rel=1e-5, abs=1e-4)


def test_a_batch_split_among_threads_gives_each_pose_its_own_value():
    from certpose.model.likelihood import _PARALLEL_MIN_TERMS, _pool

    rng, scene, cls, obj = _world(0)
    lik = PoseLikelihood(scene, cls, obj)
    centre = scene.origin + np.asarray(scene.shape) * scene.voxel_size / 2
    # Enough point terms for every thread of the pool (split in order, joined in order).
    n = 2 * max(_pool()[1], 2) * _PARALLEL_MIN_TERMS // lik.num_points + 7
    poses = _random_poses(rng, n, centre, 0.06)
    batch = lik(poses)
    np.testing.assert_array_equal(batch, [lik(T) for T in poses])
    np.testing.assert_array_equal(lik(poses[::-1]), batch[::-1])
    assert np.unique(batch).size > n // 2


def test_batch_of_close_poses_equals_slow_reference_loop():
    """Poses a few millimetres apart (a refinement's finite-difference poses) put a point in the
    cell of the pose before most of the time, where the kernel reuses the cell's corner values:
    the values are still the reference's, for every pose (crossing into other cells and back)
    and every point (the kept values are never another point's)."""
    rng, scene, cls, obj = _world(2)
    params = LikelihoodParams(beta=1.3, c_empty=-6.0, log_p_unobserved=math.log(0.3))
    lik = PoseLikelihood(scene, cls, obj, params=params)
    centre = scene.origin + np.asarray(scene.shape) * scene.voxel_size / 2
    T0 = _random_poses(rng, 1, centre, 0.01)[0]
    # A random walk of 70 small steps (0.5-3 mm at the points) and back steps.
    poses = [T0]
    for _ in range(69):
        step = make_transform(Rotation.from_rotvec(rng.normal(scale=0.01, size=3)).as_matrix(),
                              rng.normal(scale=0.001, size=3))
        poses.append(poses[-1] @ step if rng.random() < 0.7 else poses[-2])
    poses = np.stack(poses)
    # Most consecutive poses keep a point in its cell (so the reuse is exercised).
    cell = np.floor((np.einsum("bij,nj->bni", poses[:, :3, :3], obj.points) + poses[:, None, :3, 3]
                     - scene.origin) / scene.voxel_size - 0.5)
    same = np.all(cell[1:] == cell[:-1], axis=2).mean()
    assert 0.5 < same < 0.99
    slow = np.array([_reference(scene, cls, obj, T, params) for T in poses])
    np.testing.assert_allclose(lik(poses), slow, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(lik(poses[:12]), slow[:12], rtol=1e-5, atol=1e-4)  # one thread
    for b in (0, 33, 69):
        assert lik.point_terms(poses[b]).sum() == pytest.approx(slow[b], rel=1e-5, abs=1e-4)


def _stencils(rng, centre, hypotheses: int = 5, step: float = 0.004):
    """Finite-difference stencils as the refinement batches them: for each of a few poses, the
    12 poses one ``step`` (metres, or radians over 0.1 m) along each chart axis, both ways."""
    out = []
    for T0 in _random_poses(rng, hypotheses, centre, 0.01):
        for sign in (1.0, -1.0):
            for axis in range(6):
                x = np.zeros(6)
                x[axis] = sign * (step if axis < 3 else step / 0.1)
                out.append(T0 @ make_transform(Rotation.from_rotvec(x[3:]).as_matrix(), x[:3]))
    return np.stack(out)


def test_a_batch_of_stencils_gives_each_pose_its_value_alone_bit_for_bit():
    """Within a block of poses the kernel keeps the corner values of up to 8 cells per point
    (one per parity of the cell's coordinates) and reuses them when a later pose puts the point
    in one of those cells again: a stencil sends points back and forth between neighbouring
    cells. Each pose's value is still the one it gets alone (no reuse), bit for bit."""
    rng, scene, cls, obj = _world(4, p_states=(0.2, 0.3, 0.5))
    lik = PoseLikelihood(scene, cls, obj)
    centre = scene.origin + np.asarray(scene.shape) * scene.voxel_size / 2
    poses = _stencils(rng, centre)
    cell = np.floor((np.einsum("bij,nj->bni", poses[:, :3, :3], obj.points) + poses[:, None, :3, 3]
                     - scene.origin) / scene.voxel_size - 0.5).astype(int)
    # Points come back to a cell they left within a block (A, B, ..., A), the reuse exercised.
    back = [(b, n) for n in range(len(obj)) for b in range(2, 32)
            if np.any(np.all(cell[:b - 1, n] == cell[b, n], axis=1))
            and np.any(cell[b - 1, n] != cell[b, n])]
    assert len(back) > 50
    alone = np.array([lik(T) for T in poses])
    np.testing.assert_array_equal(lik(poses), alone)
    np.testing.assert_array_equal(lik(poses[::-1]), alone[::-1])
    slow = np.array([_reference(scene, cls, obj, T, lik.params) for T in poses[:24:5]])
    np.testing.assert_allclose(alone[:24:5], slow, rtol=1e-5, atol=1e-4)


def test_point_terms_sum_to_eq1_and_keep_model_order():
    rng, scene, cls, obj = _world(1)
    lik = PoseLikelihood(scene, cls, obj)
    centre = scene.origin + np.asarray(scene.shape) * scene.voxel_size / 2
    T = _random_poses(rng, 1, centre, 0.01)[0]
    terms = lik.point_terms(T)
    assert terms.shape == (len(obj),)
    assert terms.sum() == pytest.approx(lik(T), rel=1e-9, abs=1e-9)
    # Each term is that of the one-point object (the kernel reorders points internally).
    for i in (0, 17, 59):
        one = ObjectModel(obj.points[[i, i, i]], obj.descriptors[[i, i, i]])
        assert PoseLikelihood(scene, cls, one)(T) / 3 == pytest.approx(terms[i], rel=1e-5, abs=1e-6)


def test_similarity_part_matches_scene_interpolation():
    """beta * sum_i f_scn(q_i)^T z_i, with f_scn from SceneField.interpolate (z_null = 0)."""
    rng, scene, cls, obj = _world(2)
    centre = scene.origin + np.asarray(scene.shape) * scene.voxel_size / 2
    poses = _random_poses(rng, 5, centre, 0.03)
    with_sim = PoseLikelihood(scene, cls, obj, params=LikelihoodParams(beta=2.0))(poses)
    without = PoseLikelihood(scene, cls, obj, params=LikelihoodParams(beta=0.0))(poses)
    for T, a, b in zip(poses, with_sim, without, strict=True):
        q = obj.points @ T[:3, :3].T + T[:3, 3]
        sim = np.einsum("ij,ij->", scene.interpolate(q), obj.descriptors)
        assert a - b == pytest.approx(2.0 * sim, rel=1e-5, abs=1e-4)


def test_unobserved_and_empty_space_values():
    _, scene, cls, obj = _world(3)
    params = LikelihoodParams(c_empty=-7.0, log_p_unobserved=-2.0)
    lik = PoseLikelihood(scene, cls, obj, params=params)
    far = make_transform(np.eye(3), [10.0, 10.0, 10.0])
    assert lik(far) == pytest.approx(len(obj) * -2.0)
    # A scene that is all observed free space: every point pays c_empty.
    state = np.full(scene.shape, EMPTY, dtype=np.int8)
    empty_scene = SceneField(scene.voxel_size, scene.origin, scene.shape,
                             np.zeros_like(scene.descriptors), state)
    centre = scene.origin + np.asarray(scene.shape) * scene.voxel_size / 2
    tiny = ObjectModel(np.array([[0.0, 0, 0], [0.001, 0, 0], [0, 0.001, 0]]), obj.descriptors[:3])
    v = PoseLikelihood(empty_scene, cls, tiny, params=params)(make_transform(np.eye(3), centre))
    assert v == pytest.approx(3 * -7.0)


def test_free_space_erosion_only_removes_penalties():
    rng, scene, cls, obj = _world(4)
    centre = scene.origin + np.asarray(scene.shape) * scene.voxel_size / 2
    poses = _random_poses(rng, 20, centre, 0.03)
    exact = PoseLikelihood(scene, cls, obj)(poses)
    eroded = PoseLikelihood(scene, cls, obj, params=LikelihoodParams(free_space_erosion=1))(poses)
    # Turning empty voxels (c_empty) into unobserved ones (log 0.1 > c_empty) never lowers eq. (1).
    assert np.all(eroded >= exact - 1e-9)
    assert np.any(eroded > exact + 1e-6)


def test_free_space_erosion_is_repeated_dilation_by_the_cube():
    from scipy.ndimage import binary_dilation

    rng = np.random.default_rng(11)
    state = rng.choice([UNOBSERVED, EMPTY, OCCUPIED], size=(30, 26, 24), p=[0.2, 0.797, 0.003])
    for k in (1, 2, 3):
        params = LikelihoodParams(free_space_erosion=k)
        near = binary_dilation(state == OCCUPIED, np.ones((3, 3, 3), bool), iterations=k)
        eroded = (state == EMPTY) & near  # empty voxels that turn unobserved
        v = free_space_values(state, 0.01, params)
        assert np.all(v[eroded] == params.log_p_unobserved)
        assert np.all(v[(state == EMPTY) & ~near] == params.c_empty)
        assert eroded.any() and ((state == EMPTY) & ~near).any()


def test_with_object_equals_a_likelihood_built_from_scratch():
    rng, scene, cls, obj = _world(12)
    centre = scene.origin + np.asarray(scene.shape) * scene.voxel_size / 2
    poses = _random_poses(rng, 30, centre, 0.03)
    lik = PoseLikelihood(scene, cls, obj)
    sub = ObjectModel(obj.points[::3], obj.descriptors[::3], areas=np.full(20, 3e-4))
    for params in (None, LikelihoodParams(free_space_erosion=1), LikelihoodParams(c_empty=-3.0)):
        shared = lik.with_object(sub, params=params)
        fresh = PoseLikelihood(scene, cls, sub, params=params)
        np.testing.assert_array_equal(shared(poses), fresh(poses))
        assert shared.total_weight == pytest.approx(fresh.total_weight)
    np.testing.assert_array_equal(lik(poses), PoseLikelihood(scene, cls, obj)(poses))  # unchanged
    with pytest.raises(ValueError, match="Descriptor dimensions"):
        lik.with_object(ObjectModel(obj.points, np.ones((60, 3)) / np.sqrt(3)))


def test_function_form_and_shapes():
    rng, scene, cls, obj = _world(5)
    centre = scene.origin + np.asarray(scene.shape) * scene.voxel_size / 2
    poses = _random_poses(rng, 4, centre, 0.02)
    out = log_likelihood(scene, cls, obj, poses)
    assert out.shape == (4,)
    assert isinstance(log_likelihood(scene, cls, obj, poses[0]), float)


def test_bad_input_errors():
    rng, scene, cls, obj = _world(6)
    lik = PoseLikelihood(scene, cls, obj)
    with pytest.raises(ValueError, match=r"\(4, 4\) or \(B, 4, 4\)"):
        lik(np.eye(3))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        lik(bad)
    other = ObjectModel(obj.points, _unit_rows(rng, len(obj), 5))
    with pytest.raises(ValueError, match="Descriptor dimensions differ"):
        PoseLikelihood(scene, cls, other)
    wrong = ObjectClassification(np.zeros((2, 2, 2)), np.zeros((2, 2, 2), bool), -5.0, "t",
                                 ClassifierStatus.OK, "")
    with pytest.raises(ValueError, match="grid shape"):
        PoseLikelihood(scene, wrong, obj)
    nan_log_p = cls.log_p.copy()
    nan_log_p[scene.state == OCCUPIED] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        PoseLikelihood(scene, ObjectClassification(nan_log_p, cls.positive, -5.0, "t",
                                                   ClassifierStatus.OK, ""), obj)


@pytest.mark.parametrize(
    "kwargs, match",
    [({"beta": -1.0}, "beta"), ({"c_empty": 0.0}, "c_empty"), ({"log_p_unobserved": 0.5}, "log_p"),
     ({"beta": float("nan")}, "finite"), ({"free_space_erosion": -1}, "erosion"),
     ({"free_space_tolerance": -0.001}, "free_space_tolerance"),
     ({"free_space_ramp": -0.001}, "free_space_ramp"),
     ({"free_space_ramp": float("inf")}, "finite")],
)
def test_params_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LikelihoodParams(**kwargs)


def test_object_model_rejects_nan_and_unnormalised_descriptors():
    pts = np.random.default_rng(0).normal(size=(5, 3))
    d = np.eye(5)
    d[2, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ObjectModel(pts, d)
    with pytest.raises(ValueError, match="L2-normalised"):
        ObjectModel(pts, 2 * np.eye(5))
    with pytest.raises(ValueError, match=r"shape \(5, d\)"):
        ObjectModel(pts, np.eye(4))


def _plane_scene(depth: int = 12, vs: float = 0.005) -> SceneField:
    """An observed surface (occupied plane k = 0) with observed free space above it (k >= 1),
    except one unobserved column."""
    shape = (3, 3, depth)
    state = np.full(shape, EMPTY, dtype=np.int8)
    state[:, :, 0] = OCCUPIED
    state[2, 2, 1:] = UNOBSERVED
    desc = np.zeros((*shape, 2))
    desc[:, :, 0, 0] = 1.0
    return SceneField(vs, np.zeros(3), shape, desc, state)


def test_free_space_values_graded_by_distance_to_the_surface():
    scene = _plane_scene()
    lpu, c = math.log(0.1), -30.0
    params = LikelihoodParams(c_empty=c, free_space_tolerance=0.0075, free_space_ramp=0.01,
                              free_space_from="surface")
    v = free_space_values(scene.state, scene.voxel_size, params)
    # Column (1, 1): k voxels above the plane is k * 5 mm from the surface. Tolerant up to
    # 7.5 mm, then linear to c_empty at 17.5 mm, c_empty beyond.
    expected = [0.0, lpu, lpu + 0.25 * (c - lpu), lpu + 0.75 * (c - lpu)] + [c] * 8
    np.testing.assert_allclose(v[1, 1], expected, atol=1e-12)
    assert np.all(v[1, 1, 4:] == c)  # exactly: the kernel's fast path for deep free space
    np.testing.assert_allclose(v[2, 2, 1:], lpu)  # unobserved voxels keep the prior
    # No tolerance, no ramp: the ungraded model, every free voxel pays c_empty.
    v0 = free_space_values(scene.state, scene.voxel_size,
                           LikelihoodParams(c_empty=c, free_space_tolerance=0, free_space_ramp=0))
    np.testing.assert_allclose(v0[1, 1, 1:], c)
    # A ramp of 0 is a step at the tolerance.
    step = free_space_values(scene.state, scene.voxel_size,
                             LikelihoodParams(c_empty=c, free_space_tolerance=0.012,
                                              free_space_ramp=0, free_space_from="surface"))
    np.testing.assert_allclose(step[1, 1, 1:4], [lpu, lpu, c])
    # No observed surface at all: free space is deep everywhere.
    none = np.where(scene.state == OCCUPIED, EMPTY, scene.state)
    np.testing.assert_allclose(free_space_values(none, scene.voxel_size, params)[0, 0], c)
    with pytest.raises(ValueError, match=r"\(X, Y, Z\)"):
        free_space_values(np.zeros((3, 3)), 0.005, params)


def test_free_space_graded_from_the_free_regions_boundary():
    # "boundary": the distance counts to the nearest voxel that is not observed free space, so
    # free voxels beside the unobserved column (2, 2) are spared as well as those on the plane,
    # and the grid's faces (outside is unobserved) are a boundary too.
    scene = _plane_scene()
    lpu, c = math.log(0.1), -30.0
    params = LikelihoodParams(c_empty=c, free_space_tolerance=0.0075, free_space_ramp=0,
                              free_space_from="boundary")
    v = free_space_values(scene.state, scene.voxel_size, params)
    surface = free_space_values(scene.state, scene.voxel_size, replace(params, free_space_from="surface"))
    # Column (1, 1) at k = 6: 30 mm from the plane, 7.1 mm (a diagonal step) from column (2, 2).
    assert v[1, 1, 6] == pytest.approx(lpu) and surface[1, 1, 6] == c
    # A bigger grid without the unobserved column: the centre column is 15 mm from the faces.
    big = SceneField(0.005, np.zeros(3), (5, 5, 12), np.zeros((5, 5, 12, 2)),
                     np.where(np.arange(12)[None, None, :] == 0, OCCUPIED, EMPTY).astype(np.int8)
                     * np.ones((5, 5, 1), np.int8))
    vb = free_space_values(big.state, big.voxel_size, params)
    assert vb[2, 2, 1] == pytest.approx(lpu)  # 5 mm above the plane
    assert vb[2, 2, 6] == c  # 15 mm from the nearest face, 30 mm from the plane
    assert vb[0, 2, 6] == pytest.approx(lpu)  # on a face of the grid
    with pytest.raises(ValueError, match="free_space_from"):
        LikelihoodParams(free_space_from="occupied")


def test_default_free_space_spares_one_voxel_next_to_any_boundary_and_ramps_to_full():
    # Default: depth into free space (to an observed surface, unobserved space or the grid's
    # faces) up to 5 mm costs what a hidden point costs, then linear to c_empty at 10 mm.
    p = LikelihoodParams()
    assert (p.free_space_from, p.free_space_tolerance, p.free_space_ramp) == ("boundary", 0.005, 0.005)
    lpu, c = p.log_p_unobserved, p.c_empty
    state = np.where(np.arange(12)[None, None, :] == 0, OCCUPIED, EMPTY).astype(np.int8) * np.ones(
        (7, 7, 1), np.int8)
    state[3, 5, 1:] = UNOBSERVED  # a shadow: its neighbours are spared too
    v = free_space_values(state, 0.005, p)
    assert v[3, 3, 1] == pytest.approx(lpu)  # 5 mm above the plane
    assert v[3, 2, 6] == c  # 15 mm or more from the plane, the shadow and the faces: full penalty
    assert v[3, 4, 6] == pytest.approx(lpu)  # 5 mm from the shadow
    # 7.07 mm (a diagonal step) from the shadow: 41% of the way to c_empty.
    assert v[2, 4, 6] == pytest.approx(lpu + (np.sqrt(2) - 1) * (c - lpu))
    assert v[0, 3, 6] == pytest.approx(lpu)  # on a face of the grid


def test_free_space_tolerance_spares_points_near_a_surface_only():
    scene = _plane_scene()
    lpu, c = math.log(0.1), -30.0
    cls = ObjectClassification(np.where(scene.state == OCCUPIED, math.log(0.9), -5.0),
                               scene.state == OCCUPIED, -5.0, "t", ClassifierStatus.OK, "")
    one = ObjectModel(np.zeros((3, 3)), np.tile([1.0, 0.0], (3, 1)))

    def at(k: float, params: LikelihoodParams) -> float:
        # The point at the centre of column (1, 1), k voxels above the plane.
        T = make_transform(np.eye(3), (np.array([1.5, 1.5, k + 0.5])) * scene.voxel_size)
        return PoseLikelihood(scene, cls, one, params=params)(T) / 3

    graded = LikelihoodParams(c_empty=c, free_space_tolerance=0.0075, free_space_ramp=0.01,
                              free_space_from="surface")
    exact = LikelihoodParams(c_empty=c, free_space_tolerance=0, free_space_ramp=0)
    # One voxel (5 mm, about the sensor noise) above the surface: the price of a hidden point
    # instead of c_empty.
    assert at(1, graded) == pytest.approx(lpu)
    assert at(1, exact) == pytest.approx(c)
    # Deep in free space: the full penalty either way.
    assert at(6, graded) == pytest.approx(c)
    # Half-way between voxel centres 1 and 2: the linear blend (continuous in the pose).
    assert at(1.5, graded) == pytest.approx(0.5 * lpu + 0.5 * (lpu + 0.25 * (c - lpu)))
    # On the surface itself: the classifier and the similarity, as before.
    assert at(0, graded) == pytest.approx(math.log(0.9) + 1.0)


def test_batch_equals_reference_with_graded_free_space():
    rng, scene, cls, obj = _world(7)
    params = LikelihoodParams(c_empty=-25.0, free_space_tolerance=0.012, free_space_ramp=0.015)
    lik = PoseLikelihood(scene, cls, obj, params=params)
    centre = scene.origin + np.asarray(scene.shape) * scene.voxel_size / 2
    poses = _random_poses(rng, 20, centre, 0.06)
    slow = np.array([_reference(scene, cls, obj, T, params) for T in poses])
    np.testing.assert_allclose(lik(poses), slow, rtol=1e-5, atol=1e-4)
    # Tolerance only removes penalties.
    assert np.all(slow >= np.array([_reference(scene, cls, obj, T, replace(params, free_space_tolerance=0.0,
                                                                           free_space_ramp=0.0))
                                    for T in poses]) - 1e-9)


def test_area_weighted_points():
    # Eq. (1) weighs point i by areas[i] / voxel_size**2 (surface-sampled models): one unit of
    # area per voxel face gives the unweighted sum; any other area scales the point's term.
    rng, scene, cls, obj = _world(3)
    T = _random_poses(rng, 8, np.array([0.0, 0.0, 0.25]), 0.02)
    plain = PoseLikelihood(scene, cls, obj)
    unit = PoseLikelihood(scene, cls, replace_areas(obj, np.full(len(obj), scene.voxel_size**2)))
    np.testing.assert_allclose(unit(T), plain(T), rtol=1e-12, atol=1e-9)
    assert plain.total_weight == len(obj) and unit.total_weight == pytest.approx(len(obj))
    w = rng.uniform(0.2, 3.0, len(obj))
    weighted = PoseLikelihood(scene, cls, replace_areas(obj, w * scene.voxel_size**2))
    assert weighted.total_weight == pytest.approx(w.sum())
    for Tk in T[:3]:
        terms = plain.point_terms(Tk)
        np.testing.assert_allclose(weighted.point_terms(Tk), w * terms, rtol=1e-9, atol=1e-9)
        assert weighted(Tk) == pytest.approx(float(w @ terms), rel=1e-9, abs=1e-7)
        ref = [_reference(scene, cls, obj.select([i, i, i]), Tk, LikelihoodParams()) / 3
               for i in range(len(obj))]
        assert weighted(Tk) == pytest.approx(float(w @ ref), abs=1e-5)
    np.testing.assert_allclose(weighted(T), [float(w @ plain.point_terms(Tk)) for Tk in T], rtol=1e-9,
                               atol=1e-7)


def replace_areas(obj: ObjectModel, areas: np.ndarray) -> ObjectModel:
    return ObjectModel(obj.points, obj.descriptors, obj.colors, obj.normals, obj.name, areas)


def _edt_free_space_values(state, voxel_size, params):
    """free_space_values as it was, through scipy's full distance transform (the reference)."""
    from scipy.ndimage import distance_transform_edt

    occupied, empty = state == OCCUPIED, state == EMPTY
    out = np.full(state.shape, params.log_p_unobserved)
    out[occupied] = 0.0
    if params.free_space_from == "boundary":
        d = distance_transform_edt(np.pad(empty, 1), sampling=voxel_size)[1:-1, 1:-1, 1:-1][empty]
    else:
        d = distance_transform_edt(~occupied, sampling=voxel_size)[empty]
    frac = np.clip((d - params.free_space_tolerance) / params.free_space_ramp, 0.0, 1.0) \
        if params.free_space_ramp > 0 else (d > params.free_space_tolerance).astype(float)
    graded = params.log_p_unobserved + frac * (params.c_empty - params.log_p_unobserved)
    out[empty] = np.where(frac >= 1.0, params.c_empty, graded)
    return out


@pytest.mark.parametrize("seed", range(6))
def test_graded_free_space_equals_the_full_distance_transform(seed):
    # The bounded search over nearby offsets replaces scipy's transform: the same values, bit for
    # bit at the default reach (two voxels), within rounding at others; grids of every shape,
    # outside counted as boundary or not.
    rng = np.random.default_rng(seed)
    for _ in range(25):
        shape = tuple(int(n) for n in rng.integers(1, 13, 3))
        state = rng.choice([UNOBSERVED, EMPTY, OCCUPIED], size=shape,
                           p=rng.dirichlet([1, 3, 1])).astype(np.int8)
        if not (state == OCCUPIED).any():
            state.flat[0] = OCCUPIED
        for frm in ("boundary", "surface"):
            default = LikelihoodParams(free_space_from=frm)
            assert np.array_equal(free_space_values(state, 0.005, default),
                                  _edt_free_space_values(state, 0.005, default))
            tol, ramp = rng.uniform(0, 0.012), rng.choice([0.0, rng.uniform(0.001, 0.01)])
            p = LikelihoodParams(free_space_from=frm, free_space_tolerance=tol, free_space_ramp=ramp)
            vs = float(rng.choice([0.004, 0.005, 0.0075]))
            np.testing.assert_allclose(free_space_values(state, vs, p),
                                       _edt_free_space_values(state, vs, p), rtol=1e-12, atol=1e-12)


def _sparse_world(seed: int, shape=(20, 18, 16), d: int = 5):
    """Mostly observed free space with a few surface and unobserved voxels: free space several
    voxels deep, so the point-relative ramp sees every depth."""
    return _world(seed, shape, d, p_states=(0.003, 0.99, 0.007), voxel=0.005,
                  origin=(-0.05, -0.045, 0.2), n_points=50, spread=0.015)


@pytest.mark.parametrize("kwargs", [
    {},
    {"free_space_ramp": 0.0},
    {"free_space_from": "surface", "free_space_tolerance": 0.002, "free_space_ramp": 0.008},
    {"c_empty": -30.0, "free_space_ramp": 0.001, "free_space_tolerance": 0.0},
])
def test_free_space_at_point_equals_the_reference(kwargs):
    rng, scene, cls, obj = _sparse_world(21)
    params = LikelihoodParams(free_space_at="point", **kwargs)
    lik = PoseLikelihood(scene, cls, obj, params=params)
    centre = scene.origin + np.asarray(scene.shape) * scene.voxel_size / 2
    poses = _random_poses(rng, 24, centre, 0.02)
    # And poses within a millimetre of each other (a point stays in its cell from one pose to
    # the next: the kernel keeps the cell's corner values and distances).
    close = poses[0] @ np.stack([make_transform(Rotation.from_rotvec(rng.normal(scale=0.01, size=3)).as_matrix(),
                                                rng.normal(scale=0.0005, size=3)) for _ in range(20)])
    poses = np.concatenate([poses, close])
    fast = lik(poses)
    slow = np.array([_reference(scene, cls, obj, T, params) for T in poses])
    np.testing.assert_allclose(fast, slow, rtol=1e-6, atol=1e-6)
    assert lik.point_terms(poses[3]).sum() == pytest.approx(fast[3], rel=1e-9, abs=1e-9)
    # with_object switching to and from the option gives the likelihoods built from scratch.
    voxel = replace(params, free_space_at="voxel")
    np.testing.assert_allclose(lik.with_object(obj, params=voxel)(poses),
                               PoseLikelihood(scene, cls, obj, params=voxel)(poses), rtol=1e-12)
    back = PoseLikelihood(scene, cls, obj, params=voxel).with_object(obj, params=params)
    np.testing.assert_allclose(back(poses), fast, rtol=1e-12)
    # It differs from the voxel-centre ramp (the test sees the option at all).
    assert np.max(np.abs(fast - PoseLikelihood(scene, cls, obj, params=voxel)(poses))) > 1.0


def test_free_space_at_point_charges_a_point_only_past_the_tolerance():
    # A plane of surface at z = 0 and a shadow column (3, 5, z >= 1), voxels of 5 mm: free voxel
    # (2, 4, z) is 7.07 mm from the shadow, (2, 5) and (3, 4) 5 mm. Between them and the shadow
    # a point's blended distance is 4.27 mm, i.e. it stands 1.8 mm deep in free space.
    vs = 0.005
    state = np.where(np.arange(12)[None, None, :] == 0, OCCUPIED, EMPTY).astype(np.int8) * np.ones(
        (7, 7, 1), np.int8)
    state[3, 5, 1:] = UNOBSERVED
    scene = SceneField(vs, np.zeros(3), state.shape, np.zeros((*state.shape, 2)), state)
    cls = ObjectClassification(np.full(state.shape, math.log(0.9)), state == OCCUPIED, -5.0, "t",
                               ClassifierStatus.OK, "")
    one = ObjectModel(np.zeros((3, 3)), np.tile([[1.0, 0.0]], (3, 1)))  # one point, three times

    def at(ijk, params):  # eq. (1) of one point at grid coordinates ijk (voxel centres integer)
        T = make_transform(np.eye(3), (np.asarray(ijk, dtype=float) + 0.5) * vs)
        return PoseLikelihood(scene, cls, one, params=params)(T) / 3

    voxel, point = LikelihoodParams(), LikelihoodParams(free_space_at="point")
    lpu, c = voxel.log_p_unobserved, voxel.c_empty
    shallow = (2.5, 4.5, 6.0)
    # The voxel-centre ramp charges it (a quarter of (2, 4)'s 41%); the point-relative one does not.
    assert at(shallow, voxel) == pytest.approx(lpu + 0.25 * (np.sqrt(2) - 1) * (c - lpu))
    assert at(shallow, point) == pytest.approx(lpu)
    # 5 mm above the plane, 1.5 voxels from the faces: 2.5 mm deep, spared both ways.
    assert at((3, 3, 1), point) == pytest.approx(lpu)
    # Voxel centre 10 mm from the plane (the shadow and the faces are farther): the point stands
    # 7.5 mm deep and pays (7.5 - 5) / 5 of the charge; the voxel-centre ramp reads 10 mm, all of it.
    assert at((3, 2, 2.0), point) == pytest.approx(lpu + 0.5 * (c - lpu))
    assert at((3, 2, 2.0), voxel) == pytest.approx(lpu + 1.0 * (c - lpu))
    # Deep in free space: c_empty either way.
    assert at((3, 2, 6), point) == pytest.approx(c)


def test_free_space_at_validation():
    with pytest.raises(ValueError, match="free_space_at"):
        LikelihoodParams(free_space_at="pixel")
    with pytest.raises(ValueError, match="free_space_at"):
        LikelihoodParams(free_space_at="point", free_space="pixels")
    # "auto" keeps voxels when the point-relative ramp is asked for.
    from certpose.model.likelihood import resolve_free_space

    class WithFrames:
        frames = (object(),)

    assert resolve_free_space(LikelihoodParams(free_space="auto", free_space_at="point"),
                              WithFrames()).free_space == "voxels"


@pytest.mark.parametrize("graded", [False, True])
def test_cell_codes_follow_their_definition_cell_by_cell(graded):
    from certpose.model._kernels import (
        EMPTY_CODE,
        MIXED,
        UNIFORM,
        UNIFORM_EMPTY,
        UNIFORM_UNOBSERVED,
        UNOBSERVED_CODE,
    )
    from certpose.model.likelihood import _cell_codes

    rng = np.random.default_rng(4)
    shape = (7, 6, 5)
    # Mostly free space in blocks (so that uniform cells of every kind occur), a few occupied.
    index = np.where(rng.random(shape) < 0.5, EMPTY_CODE, UNOBSERVED_CODE).astype(np.int32)
    index[:3, :3] = UNOBSERVED_CODE
    index[3:, 3:] = EMPTY_CODE
    index[rng.random(shape) < 0.08] = 1
    background = np.where(index == UNOBSERVED_CODE, -1.5, np.where(rng.random(shape) < 0.6, -8.0, -3.0))
    background[3:, 3:] = -8.0
    background[5:, :2] = np.nan  # NaN equals nothing: never uniform
    depth = None
    if graded:  # free space charged at the point: EMPTY voxels hold c_unobs, and depths
        background[3:, 3:] = -1.5
        g = np.where(index == EMPTY_CODE, rng.choice([0.0, 0.02, 0.05], size=shape), 0.0)
        g[3:5, 3:] = 0.0
        g[5:, 3:] = 0.05
        depth = (g, 0.01, 0.0, -1.5)
    got = _cell_codes(index, background, -8.0, depth)
    assert got.shape == (6, 5, 4)
    for x, y, z in np.ndindex(got.shape):
        ci = index[x:x + 2, y:y + 2, z:z + 2].ravel()
        cb = background[x:x + 2, y:y + 2, z:z + 2].ravel()
        want = MIXED
        if np.all(ci < 0) and np.all(cb == cb[0]):
            if depth is None:
                want = UNIFORM_EMPTY if cb[0] == -8.0 else UNIFORM
            else:
                cg = depth[0][x:x + 2, y:y + 2, z:z + 2].ravel()
                want = (UNIFORM if np.all(cg <= 0.01) else
                        UNIFORM_EMPTY if np.all(cg > 0.01) and cb[0] == -1.5 else MIXED)
        if np.all(ci == UNOBSERVED_CODE):
            want = UNIFORM_UNOBSERVED
        assert got[x, y, z] == want, (x, y, z)
    assert len(np.unique(got)) >= 3
