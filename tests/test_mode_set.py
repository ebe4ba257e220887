"""The certified mode set of weighted TLS (solvers.certify.mode_set): its bounds hold on sampled
poses, it lists every near-optimal basin (a symmetric object's two), nothing within the margin
lies outside its regions (dense sampling), and a time limit claims nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from solvers import WeightedTLSProblem, solve_registration
from solvers.certify import mode_set as ms
from solvers.certify.mode_set import ModeSetParams, ModeSetStatus, certify_mode_set

BETA = 0.01


def symmetric_problem(seed: int = 0) -> tuple[WeightedTLSProblem, np.ndarray, np.ndarray]:
    """An eq. (2)-like problem of an object with a half-turn symmetry about z: each model point
    has three candidate targets (its own true position, its symmetric partner's, an outlier),
    so the true pose and the true pose turned by 180 deg about z are near-tied minima."""
    rng = np.random.default_rng(seed)
    half = rng.uniform(-0.08, 0.08, size=(6, 3))
    S = np.diag([-1.0, -1.0, 1.0])
    pts = np.concatenate([half, half @ S.T])
    T0 = np.eye(4)
    T0[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T0[:3, 3] = rng.uniform(-0.2, 0.2, 3)
    T1 = T0.copy()
    T1[:3, :3] = T0[:3, :3] @ S
    src, dst, w = [], [], []
    for p in pts:
        for target, weight in ((T0[:3, :3] @ p + T0[:3, 3], 1.5), (T1[:3, :3] @ p + T1[:3, 3], 1.5),
                               (T0[:3, 3] + rng.uniform(-0.1, 0.1, 3), rng.uniform(0.5, 2.0))):
            src.append(p)
            dst.append(target + rng.normal(scale=0.2 * BETA, size=3))
            w.append(weight)
    return WeightedTLSProblem(np.array(src), np.array(dst), noise_bound=BETA, weights=np.array(w)), T0, T1


def cost(problem: WeightedTLSProblem, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Costs of a batch of poses (R (n, 3, 3), t (n, 3))."""
    moved = np.einsum("nij,kj->nki", R, problem.source) + t[:, None, :] - problem.target
    r2 = np.einsum("nki,nki->nk", moved, moved) / problem.noise_bound**2
    return np.minimum(r2, problem.cbar2) @ problem.weights


def test_box_bounds_hold_on_poses_sampled_in_each_box():
    """The kernel's lower bound (groups' exact minima, and the rigid QP bound on small boxes)
    is at most the cost of every pose of the box; its upper bound is the centre's cost."""
    problem, T0, _ = symmetric_problem(1)
    tab = ms._tables(problem)
    rng = np.random.default_rng(5)
    v0 = Rotation.from_matrix(T0[:3, :3]).as_rotvec()
    u0 = ms._internal(T0, tab)
    bounder = ms._Bounder(tab, 1, 10.0)  # the rigid bound on every box
    checked = coupled_tight = 0
    for size in (1e-3, 3e-3, 1e-2, 3e-2, 0.1):
        boxes = np.zeros((40, 9))
        boxes[:, :3] = v0 + rng.normal(scale=size, size=(40, 3))
        boxes[:, 3] = size * rng.uniform(0.2, 1.0, 40)
        boxes[:, 4:7] = u0 + rng.normal(scale=size * 0.1, size=(40, 3))
        boxes[:, 7] = size * 0.1 * rng.uniform(0.2, 1.0, 40)
        lower, upper = bounder(boxes, np.inf)
        group_only, _ = ms._Bounder(tab, 1, 0.0)(boxes, np.inf)
        assert np.all(lower >= group_only)
        coupled_tight += int(np.sum(lower > group_only + 1e-9))
        for b in range(boxes.shape[0]):
            v = boxes[b, :3] + rng.uniform(-1, 1, (300, 3)) * boxes[b, 3]
            u = boxes[b, 4:7] + rng.uniform(-1, 1, (300, 3)) * boxes[b, 7]
            v[:8] = boxes[b, :3] + ms._CORNERS * boxes[b, 3]  # the corners too
            R = Rotation.from_rotvec(v).as_matrix()
            t = u + tab.dst_origin - R @ tab.src_origin
            f = cost(problem, R, t)
            assert f.min() >= lower[b] - 1e-9 * (1 + f.min()), (size, b)
            Rc = Rotation.from_rotvec(boxes[b, :3]).as_matrix()
            fc = cost(problem, Rc[None], (boxes[b, 4:7] + tab.dst_origin - Rc @ tab.src_origin)[None])
            assert upper[b] == pytest.approx(float(fc[0]), rel=1e-9)
            checked += 1
    assert checked == 200 and coupled_tight > 10  # the rigid bound does tighten small boxes


def test_two_near_tied_minima_are_both_listed():
    problem, T0, T1 = symmetric_problem(0)
    start = solve_registration(problem).T_target_source  # one of the two
    res = certify_mode_set(problem, start, params=ModeSetParams(time_limit=120, margin=0.05))
    assert res.success and res.status is ModeSetStatus.CERTIFIED, res.message
    c0, c1 = (float(cost(problem, T[None, :3, :3], T[None, :3, 3])[0]) for T in (T0, T1))
    assert abs(c0 - c1) < 0.05 * max(c0, c1)  # near-tied
    assert c0 <= res.best_cost + res.margin and c1 <= res.best_cost + res.margin
    hit0 = [k for k, r in enumerate(res.regions) if r.contains(T0)]
    hit1 = [k for k, r in enumerate(res.regions) if r.contains(T1)]
    assert hit0 and hit1 and not set(hit0) & set(hit1)  # two separate regions
    for k in hit0 + hit1:
        assert np.degrees(res.regions[k].rotation_radius) < 45
    assert res.lower_bound <= res.best_cost and 0 <= res.literature_gap < 1


def test_no_sampled_pose_within_the_margin_lies_outside_the_regions():
    problem, T0, T1 = symmetric_problem(2)
    res = certify_mode_set(problem, T0, params=ModeSetParams(time_limit=120, margin=0.05))
    assert res.success, res.message
    rng = np.random.default_rng(0)
    thr = res.best_cost + res.margin
    inside_thr = 0
    for centre in (T0, T1, None):
        n = 100_000
        if centre is None:  # anywhere: uniform rotations, translations about the targets
            R = Rotation.random(n, random_state=1).as_matrix()
            t = problem.target.mean(axis=0) - np.einsum("nij,j->ni", R, problem.source.mean(axis=0))
            t += rng.uniform(-0.05, 0.05, (n, 3))
        else:  # dense about a minimum, out to well beyond its region
            ang = np.radians(25) * rng.random(n) ** 2
            axis = rng.normal(size=(n, 3))
            axis /= np.linalg.norm(axis, axis=1, keepdims=True)
            R = Rotation.from_rotvec(axis * ang[:, None]).as_matrix() @ centre[:3, :3]
            c = problem.source.mean(axis=0)
            t = (centre[:3, :3] @ c + centre[:3, 3] - np.einsum("nij,j->ni", R, c)
                 + rng.uniform(-3, 3, (n, 3)) * BETA * rng.random((n, 1)) ** 2)
        f = cost(problem, R, t)
        assert f.min() >= res.lower_bound - 1e-9
        for k in np.flatnonzero(f <= thr):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R[k], t[k]
            assert res.contains(T), (f[k], thr)
            inside_thr += 1
    assert inside_thr > 1000  # the check is not vacuous


def test_tiny_time_budget_claims_nothing():
    problem, T0, _ = symmetric_problem(0)
    res = certify_mode_set(problem, T0, params=ModeSetParams(time_limit=1e-4))
    assert not res.success and res.status is ModeSetStatus.TIME_LIMIT
    assert res.regions == () and not res.contains(T0)
    assert res.lower_bound <= res.best_cost and np.isfinite(res.literature_gap)
    assert "no mode set claimed" in res.message
    d = json.loads(json.dumps(res.to_dict(), allow_nan=False))
    assert d["status"] == "time_limit" and d["regions"] == [] and not d["success"]


def test_regions_move_with_the_frame():
    problem, T0, _ = symmetric_problem(0)
    res = certify_mode_set(problem, T0, params=ModeSetParams(time_limit=120))
    assert res.success
    A = np.eye(4)
    A[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    A[:3, 3] = [0.1, 0.2, -0.3]
    moved = res.moved(A)
    rng = np.random.default_rng(3)
    for r, m in zip(res.regions, moved.regions, strict=True):
        for _ in range(200):  # poses of the region, mapped, lie in the moved region
            w = rng.normal(size=3)
            w *= rng.random() * r.rotation_radius / np.linalg.norm(w)
            T = np.eye(4)
            T[:3, :3] = Rotation.from_rotvec(w).as_matrix() @ r.rotation
            T[:3, 3] = r.translation + rng.uniform(-1, 1, 3) * r.translation_half_width
            assert r.contains(T) and m.contains(A @ T)
    d = moved.to_dict()
    assert d["status"] == "certified" and len(d["regions"]) == len(res.regions)


def test_bad_inputs():
    problem, T0, _ = symmetric_problem(0)
    with pytest.raises(ValueError, match=r"Expected `candidates` to have shape"):
        certify_mode_set(problem, np.eye(3))
    with pytest.raises(TypeError, match="WeightedTLSProblem"):
        certify_mode_set(problem.source, T0)  # type: ignore[arg-type]
    for bad in ({"margin": -0.1}, {"resolution": 0.0}, {"time_limit": 0.0}, {"threads": 0}):
        with pytest.raises(ValueError):
            ModeSetParams(**bad)


def test_a_margin_reaching_the_all_outlier_cost_is_said_so():
    problem, T0, _ = symmetric_problem(0)
    res = certify_mode_set(problem, T0, params=ModeSetParams(margin=10.0))
    assert res.status is ModeSetStatus.NO_MARGIN and not res.success


def test_undecided_boxes_are_covered_by_the_final_regions():
    """Boxes the search leaves undecided join a region they touch or start their own; every
    pose of every box lies in the final regions (original coordinates)."""
    problem, T0, _ = symmetric_problem(0)
    tab = ms._tables(problem)
    rng = np.random.default_rng(4)
    seeds = ms._seed_regions(problem, tab, T0[None], 30.0, 31.0, BETA, rng)
    v0 = Rotation.from_matrix(T0[:3, :3]).as_rotvec()
    u0 = ms._internal(T0, tab)
    boxes = np.zeros((60, 9))
    boxes[:, :3] = v0 + rng.normal(scale=0.5, size=(60, 3))  # some touch the seed, most not
    boxes[:, 3] = rng.uniform(0.005, 0.05, 60)
    boxes[:, 4:7] = u0 + rng.normal(scale=0.02, size=(60, 3))
    boxes[:, 7] = rng.uniform(0.001, 0.005, 60)
    regions = ms._final_regions(seeds, boxes, rng.uniform(0, 1, 60), tab)
    assert len(regions) > 1
    for b in boxes:
        for _ in range(20):
            v = b[:3] + rng.uniform(-1, 1, 3) * b[3]
            R = Rotation.from_rotvec(v).as_matrix()
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = b[4:7] + rng.uniform(-1, 1, 3) * b[7] + tab.dst_origin - R @ tab.src_origin
            assert any(r.contains(T) for r in regions)


def test_box_limit_claims_nothing_and_its_bound_holds():
    """Stopped on the kept boxes' limit: no regions, and the lower bound still bounds the
    problem (the boxes of the batch it stopped in count)."""
    problem, T0, T1 = symmetric_problem(0)
    best = solve_registration(problem).cost
    for resolution in (3.0, 1.0, 0.5):
        for limit in (1, 10, 100, 1000):
            res = certify_mode_set(problem, T0, params=ModeSetParams(
                resolution=resolution, max_kept_boxes=limit, time_limit=60))
            if res.status is ModeSetStatus.CERTIFIED:
                continue
            assert res.status is ModeSetStatus.BOX_LIMIT and not res.success
            assert res.regions == ()
            assert res.lower_bound <= min(best, res.best_cost) + 1e-9, (resolution, limit)


def test_the_kernel_is_called_with_its_declared_signature_only():
    """A second signature would be a second compilation on a first run."""
    from solvers import jit

    problem, T0, _ = symmetric_problem(0)
    certify_mode_set(problem, T0)
    (spec,) = jit.declared(["solvers.certify._mode_kernels"])
    sigs = spec.dispatcher().signatures
    assert sigs and all(tuple(s) == spec.signature for s in sigs), sigs


@pytest.mark.slow  # the demo's pose pipeline first
def test_demo_eq2_problem_no_sampled_pose_within_the_margin_outside_the_regions():
    """On the demo's own eq. (2) problem (a real one: 350 terms, near-ties along the mug's
    axis), dense sampling about the minimiser and far from it finds no pose within the margin
    outside the regions, and none below the lower bound."""
    from certpose.estimation.pipeline import run_demo

    res = run_demo(rng=0)
    problem = res.mle.eq2_problem.problem
    T0 = res.mle.eq2_result.T_target_source
    ms_res = certify_mode_set(problem, T0, params=ModeSetParams(time_limit=120))
    assert ms_res.success, ms_res.message
    thr = ms_res.best_cost + ms_res.margin
    rng = np.random.default_rng(0)
    c = problem.source.mean(axis=0)
    below = 0
    for spread, shift, n in ((np.radians(10), 0.005, 100_000), (np.radians(45), 0.03, 100_000)):
        ang = spread * rng.random(n) ** 2
        axis = rng.normal(size=(n, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        R = Rotation.from_rotvec(axis * ang[:, None]).as_matrix() @ T0[:3, :3]
        t = (T0[:3, :3] @ c + T0[:3, 3] - np.einsum("nij,j->ni", R, c)
             + rng.uniform(-shift, shift, (n, 3)) * rng.random((n, 1)) ** 2)
        for lo in range(0, n, 20_000):
            f = cost(problem, R[lo:lo + 20_000], t[lo:lo + 20_000])
            assert f.min() >= ms_res.lower_bound - 1e-6
            for k in np.flatnonzero(f <= thr):
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = R[lo + k], t[lo + k]
                assert ms_res.contains(T), (f[k], thr)
                below += 1
    assert below > 100  # not vacuous


def test_pose_params_take_mode_set_params_only():
    from certpose.estimation.pipeline import PoseParams

    assert PoseParams(mode_set=ModeSetParams(time_limit=5)).mode_set.time_limit == 5
    with pytest.raises(TypeError, match="ModeSetParams"):
        PoseParams(mode_set=10.0)


def ring_problem(seed: int = 0, n: int = 12) -> tuple[WeightedTLSProblem, np.ndarray]:
    """An eq. (2)-like problem of a body of revolution: two rings of ``n`` points about z, each
    point with every point of its ring as a candidate target, so the ``n`` turns of the true pose
    about z are tied minima (a can's or a marker's ring)."""
    rng = np.random.default_rng(seed)
    a = np.arange(n) * 2 * np.pi / n
    T0 = np.eye(4)
    T0[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T0[:3, 3] = rng.uniform(-0.2, 0.2, 3)
    src, dst = [], []
    for z in (-0.03, 0.03):
        ring = np.c_[0.05 * np.cos(a), 0.05 * np.sin(a), np.full(n, z)]
        for p in ring:
            for q in ring @ T0[:3, :3].T + T0[:3, 3]:
                src.append(p)
                dst.append(q + rng.normal(scale=0.2 * BETA, size=3))
    return WeightedTLSProblem(np.array(src), np.array(dst), noise_bound=BETA), T0


def test_a_ring_of_minima_is_covered_by_few_wide_regions(monkeypatch):
    """Near-optimal poses as far out as the seed's sampling reaches widen it: a ring of tied
    minima ends in a few wide regions, with fewer boxes bounded than narrow regions need, and
    every turn of the ring (and every sampled pose within the margin) inside them."""
    problem, T0 = ring_problem()
    params = ModeSetParams(time_limit=300, margin=0.02)
    res = certify_mode_set(problem, T0, params=params)
    assert res.success and res.status is ModeSetStatus.CERTIFIED, res.message
    assert len(res.regions) <= 3 and max(r.rotation_radius for r in res.regions) > np.radians(60)
    rng = np.random.default_rng(1)
    n = 60_000
    turns = 30.0 * rng.integers(0, 12, (n, 1)) + rng.normal(scale=4.0, size=(n, 1))
    twist = Rotation.from_euler("z", turns, degrees=True).as_matrix()
    tilt = Rotation.from_rotvec(rng.normal(scale=np.radians(1.0), size=(n, 3))).as_matrix()
    R = T0[:3, :3] @ twist @ tilt
    t = T0[:3, 3] + rng.normal(scale=0.3 * BETA, size=(n, 3))
    f = cost(problem, R, t)
    thr = res.best_cost + res.margin
    assert np.sum(f <= thr) > 500  # the check is not vacuous
    for k in np.flatnonzero(f <= thr):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R[k], t[k]
        assert res.contains(T), (f[k], thr)
    for deg in range(0, 360, 30):
        T = T0.copy()
        T[:3, :3] = T0[:3, :3] @ Rotation.from_euler("z", deg, degrees=True).as_matrix()
        assert res.contains(T), deg
    monkeypatch.setattr(ms, "_MAX_SAMPLE_ANGLE", ms._SAMPLE_ANGLE)  # regions sized within 30 deg
    narrow = certify_mode_set(problem, T0, params=params)
    assert narrow.success and len(narrow.regions) > 2 * len(res.regions)
    assert res.boxes_explored < 0.8 * narrow.boxes_explored
