"""Eq. (2): weights, mapping and sparsification; refinement and search on eq. (1)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose.estimation.mle import (
    Eq2Params,
    MLEParams,
    build_eq2_problem,
    coarse_search,
    estimate_mle,
    global_search,
    refine_pose,
    solve_eq2,
)
from certpose.geometry.objects import ObjectModel
from certpose.model.classifier import ClassifierStatus, ObjectClassification
from certpose.model.eq2 import WIDE_EQ2
from certpose.model.grid import EMPTY, OCCUPIED
from certpose.model.likelihood import LikelihoodParams, PoseLikelihood
from certpose.model.scene import SceneField
from solvers.lie import make_transform, rotation_error_deg
from tests.conftest import box_surface


def _unit_rows(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    x = rng.normal(size=(n, d))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _box_object(rng: np.random.Generator, d: int = 6) -> ObjectModel:
    """Points on the surface of an asymmetric box (4 x 3 x 2 cm) with distinct descriptors."""
    p = box_surface(rng, np.array([0.04, 0.03, 0.02]), 40)
    return ObjectModel(p, _unit_rows(rng, p.shape[0], d))


def _scene_with_object(obj: ObjectModel, T: np.ndarray, vs: float = 0.005):
    """A scene whose occupied voxels are the transformed object's points (with their
    descriptors), empty space elsewhere in the box; the classifier marks them positive."""
    q = obj.points @ T[:3, :3].T + T[:3, 3]
    origin = q.min(axis=0) - 0.03
    shape = tuple(int(s) for s in np.ceil((q.max(axis=0) + 0.03 - origin) / vs))
    state = np.full(shape, EMPTY, dtype=np.int8)
    desc = np.zeros((*shape, obj.dim))
    idx = np.floor((q - origin) / vs).astype(int)
    acc: dict[tuple[int, int, int], list[np.ndarray]] = {}
    for i, ijk in enumerate(map(tuple, idx)):
        acc.setdefault(ijk, []).append(obj.descriptors[i])
    for ijk, ds in acc.items():
        m = np.mean(ds, axis=0)
        desc[ijk] = m / np.linalg.norm(m)
        state[ijk] = OCCUPIED
    scene = SceneField(vs, origin, shape, desc, state)
    log_p = np.where(state == OCCUPIED, math.log(0.9), -5.0)
    cls = ObjectClassification(log_p, state == OCCUPIED, -5.0, "test", ClassifierStatus.OK, "")
    return scene, cls


def test_eq2_weights_are_the_documented_mapping():
    rng = np.random.default_rng(0)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), [0.1, 0.0, 0.5])
    scene, cls = _scene_with_object(obj, T)
    beta = 1.3
    eq2 = build_eq2_problem(scene, cls, obj, params=Eq2Params(num_object_points=30, top_k=5),
                            likelihood_params=LikelihoodParams(beta=beta), rng=0)
    prob = eq2.problem
    assert prob.n == 30 * 5
    # Non-negative weights, w = c - c_floor with c_floor = c_min - beta.
    assert np.all(prob.weights >= 0)
    assert eq2.c_floor == pytest.approx(-5.0 - beta)
    np.testing.assert_allclose(prob.weights, eq2.c - eq2.c_floor, rtol=1e-6, atol=1e-6)
    # c_ij recomputed independently: log p_O(y_j) + beta * f_scn(y_j)^T z_i at voxel centres.
    occ = np.argwhere(scene.state == OCCUPIED)
    ijk = occ[eq2.grid_index]
    c_ref = (cls.log_p[tuple(ijk.T)]
             + beta * np.einsum("kd,kd->k", scene.descriptors[tuple(ijk.T)],
                                obj.descriptors[eq2.object_index]))
    np.testing.assert_allclose(eq2.c, c_ref, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(prob.target, scene.grid_to_world(ijk.astype(float)), atol=1e-12)
    np.testing.assert_allclose(prob.source, obj.points[eq2.object_index], atol=1e-12)
    # Top-k: for each object point, no dropped grid point has a larger c than a kept one.
    all_c = (cls.log_p[tuple(occ.T)][None, :]
             + beta * obj.descriptors[eq2.object_index[::5]] @ scene.descriptors[tuple(occ.T)].T)
    kept_min = eq2.c.reshape(30, 5).min(axis=1)
    for row in range(30):
        dropped = np.setdiff1d(np.arange(occ.shape[0]), eq2.grid_index[row * 5:(row + 1) * 5])
        assert all_c[row, dropped].max() <= kept_min[row] + 1e-5


def test_eq2_solution_recovers_a_textured_pose_and_reports_certification():
    rng = np.random.default_rng(1)
    obj = _box_object(rng, d=16)
    T = make_transform(Rotation.from_rotvec([0.2, 0.4, -0.3]).as_matrix(), [0.02, -0.01, 0.45])
    scene, cls = _scene_with_object(obj, T)
    # Distinct descriptors: the top-1 candidate is right for most points.
    eq2 = build_eq2_problem(scene, cls, obj, params=Eq2Params(num_object_points=40, top_k=2),
                            rng=0)
    res = solve_eq2(eq2, certify=False)
    assert res.success, res.message
    assert rotation_error_deg(res.rotation, T[:3, :3]) < 5.0
    assert np.linalg.norm(res.translation - T[:3, 3]) < 0.005
    assert res.info["certificate_message"] == "not requested"


def test_refine_pose_never_worsens_and_climbs_back_to_the_truth():
    obj, T, scene, cls, lik = _box_case([0.1, 0.2, 0.3], [0.0, 0.0, 0.5], seed=2)
    start = T @ make_transform(Rotation.from_rotvec([0.03, -0.02, 0.02]).as_matrix(), [0.003, -0.002, 0.002])
    for method in ("L-BFGS-B", "Powell"):
        T1, v1, nfev = refine_pose(lik, start, scale=0.03, method=method)
        assert v1 >= lik(start) - 1e-9
        assert v1 == pytest.approx(lik(T1), abs=1e-6)
        assert nfev > 1
        assert np.linalg.norm(T1[:3, 3] - T[:3, 3]) < 0.004
    with pytest.raises(ValueError, match="scale"):
        refine_pose(lik, start, scale=0.0)
    with pytest.raises(ValueError, match="method"):
        refine_pose(lik, start, scale=0.03, method="CG")



def _box_case(rotvec, translation, seed=3, params=None):
    """The box of ``_box_object`` (drawn with ``seed``) at the pose ``(rotvec, translation)``
    in a hand-built scene: object, pose, scene, classifier and eq. (1) (``params``, default
    the library's)."""
    obj = _box_object(np.random.default_rng(seed))
    T = make_transform(Rotation.from_rotvec(rotvec).as_matrix(), translation)
    scene, cls = _scene_with_object(obj, T)
    return obj, T, scene, cls, PoseLikelihood(scene, cls, obj, params=params)

_UNGRADED_FREE_SPACE = LikelihoodParams(free_space_tolerance=0, free_space_ramp=0)


def test_estimate_mle_and_coarse_search_on_a_hand_built_scene():
    rng = np.random.default_rng(3)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([1.0, -0.5, 2.0]).as_matrix(), [0.01, 0.02, 0.5])
    scene, cls = _scene_with_object(obj, T)
    lik = PoseLikelihood(scene, cls, obj)
    poses, values = coarse_search(lik, obj, T[:3, 3] + T[:3, :3] @ obj.centroid,
                                  num_rotations=64, rng=0)
    assert poses.shape == (64 * 27, 4, 4) and values.shape == (64 * 27,)
    np.testing.assert_allclose(values[:5], lik(poses[:5]), rtol=1e-9)
    res = estimate_mle(scene, cls, obj, params=MLEParams(certify=False, num_rotations=512), rng=0)
    assert res.success, res.message
    assert res.log_likelihood >= lik(T) - 1.0  # at least as likely as the truth (up to polish)
    assert np.linalg.norm(res.T_scene_object[:3, 3] - T[:3, 3]) < 0.005
    assert rotation_error_deg(res.T_scene_object[:3, :3], T[:3, :3]) < 5.0
    assert math.isfinite(res.eq2_log_likelihood) and res.eq2_result is not None
    assert res.num_evaluations > 64 * 27


def test_estimate_mle_without_object_evidence():
    rng = np.random.default_rng(4)
    obj = _box_object(rng)
    scene, cls = _scene_with_object(obj, np.eye(4))
    none = ObjectClassification(np.full(cls.log_p.shape, -5.0), np.zeros(cls.log_p.shape, bool),
                                -5.0, "test", ClassifierStatus.NO_POSITIVES, "nothing")
    res = estimate_mle(scene, none, obj)
    assert not res.success and res.status.value == "no_object_evidence"


def test_global_search_returns_a_scored_pose():
    pytest.importorskip("nevergrad", reason="the global search uses the optional nevergrad extra")
    rng = np.random.default_rng(5)
    obj = _box_object(rng)
    T = make_transform(np.eye(3), [0.0, 0.0, 0.5])
    scene, cls = _scene_with_object(obj, T)
    lik = PoseLikelihood(scene, cls, obj)
    best, value = global_search(lik, T[:3, 3], radius=0.02, budget=256, batch=32, rng=0)
    assert value == pytest.approx(lik(best), rel=1e-9)
    # Better than the typical pose of its search space (random rotations and translations).
    rand = np.stack([make_transform(Rotation.from_rotvec(rng.uniform(-np.pi, np.pi, 3) / np.sqrt(3)).as_matrix(),
                                    T[:3, 3] + rng.uniform(-0.02, 0.02, 3) - obj.centroid)
                     for _ in range(256)])
    assert value > np.median(lik(rand))


@pytest.mark.parametrize("kwargs", [{"num_object_points": 2}, {"top_k": 0}, {"noise_bound": -1.0}])
def test_eq2_params_validation(kwargs):
    with pytest.raises(ValueError):
        Eq2Params(**kwargs)


def test_mle_params_validation():
    with pytest.raises(ValueError, match="num_rotations"):
        MLEParams(num_rotations=-1)
    with pytest.raises(ValueError, match="coarse_points"):
        MLEParams(coarse_points=2)
    with pytest.raises(ValueError, match="hop_starts"):
        MLEParams(hop_starts=0)
    with pytest.raises(ValueError, match="hop_translation"):
        MLEParams(hop_translation=-0.1)
    with pytest.raises(ValueError, match="num_centres"):
        MLEParams(num_centres=0)
    with pytest.raises(ValueError, match="coarse_align_iterations"):
        MLEParams(coarse_align_iterations=-1)
    with pytest.raises(ValueError, match="coarse_align_points"):
        MLEParams(coarse_align_points=0)
    with pytest.raises(ValueError, match="search_points"):
        MLEParams(search_points=2)


def test_an_exception_inside_estimate_mle_leaves_no_certifier_thread(monkeypatch):
    import threading
    import time

    import certpose.estimation.mle as mle_mod

    rng = np.random.default_rng(3)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([1.0, -0.5, 2.0]).as_matrix(), [0.01, 0.02, 0.5])
    scene, cls = _scene_with_object(obj, T)
    started = threading.Event()
    real_certify = mle_mod.certify_eq2

    def slow_certify(*args, **kwargs):
        started.set()
        time.sleep(0.5)  # still running when the search below fails
        return real_certify(*args, **kwargs)

    def failing_search(*args, **kwargs):
        assert started.wait(5.0)
        raise RuntimeError("search failed")

    import certpose.estimation.batch as batch_mod

    # The certifier starts once eq. (2)'s minimisers are refined (the one that climbed highest is
    # certified); the basin hops that follow fail.
    monkeypatch.setattr(mle_mod, "certify_eq2", slow_certify)
    monkeypatch.setattr(batch_mod, "basin_hop", failing_search)
    with pytest.raises(RuntimeError, match="search failed"):
        estimate_mle(scene, cls, obj, params=MLEParams(certify=True, num_rotations=16), rng=0)
    assert started.is_set()
    alive = [t.name for t in threading.enumerate()
             if t.name.startswith(mle_mod._Certifier.THREAD_PREFIX)]
    assert alive == []


def test_the_certifier_certifies_the_last_problem_submitted(monkeypatch):
    """The MLE submits eq. (2) again about its winner when that is not the minimiser certified
    (a near-symmetric turn): the second problem replaces the first without waiting for it (the
    search goes on), its result is the second's, and leaving the block ends both threads."""
    import threading
    import time

    import certpose.estimation.mle as mle_mod

    real_certify = mle_mod.certify_eq2

    def slow_certify(*args, **kwargs):
        time.sleep(0.3)  # the first is still running when the second is submitted
        return real_certify(*args, **kwargs)

    monkeypatch.setattr(mle_mod, "certify_eq2", slow_certify)
    from certpose.model.eq2 import solve_eq2_about_seeds

    rng = np.random.default_rng(10)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([0.2, 0.9, -0.4]).as_matrix(), [0.0, -0.01, 0.5])
    scene, cls = _scene_with_object(obj, T)
    turned = T @ make_transform(Rotation.from_rotvec([0.0, 0.0, math.pi / 2]).as_matrix(),
                                np.zeros(3))
    seeded = solve_eq2_about_seeds(scene, cls, obj, np.stack([turned, T]), rng=0,
                                   params=Eq2Params(seed_object_points=60))
    def alive() -> list:
        return [t for t in threading.enumerate()
                if t.name.startswith(mle_mod._Certifier.THREAD_PREFIX)]

    with mle_mod._Certifier() as certifier:
        certifier.submit(seeded.problems[0], seeded.results[0], 5.0)
        certifier.submit(seeded.problems[1], seeded.results[1], 5.0)
        assert len(alive()) == 2  # the first (asleep for 0.3 s) still runs: not waited for
        res = certifier.result()
    assert not alive()
    assert rotation_error_deg(res.rotation, T[:3, :3]) < 5.0
    assert rotation_error_deg(seeded.results[0].rotation, T[:3, :3]) > 45.0


@pytest.mark.parametrize("moved", [False, True])
def test_the_polish_beside_the_certifier_returns_what_the_polish_after_it_does(monkeypatch, moved):
    """The winner is polished (step 7) while the certifier finishes, before waiting for it;
    when the certifier returns another pose than it was given (``moved``: one more hypothesis,
    which may win), that polish is undone and done again after it. Either way the result is
    the reference order's (polish after the certificate) bit for bit: pose, values, modes,
    hypotheses and evaluation count."""
    import certpose.estimation.mle as mle_mod

    real_certify = mle_mod.certify_eq2

    def certify(*args, **kwargs):
        out = real_certify(*args, **kwargs)
        if not moved:
            return out
        turn = make_transform(Rotation.from_rotvec([0.0, 0.05, 0.0]).as_matrix(), [0.002, 0, 0])
        return out._with_transform(out.T_target_source @ turn)

    monkeypatch.setattr(mle_mod, "certify_eq2", certify)
    rng = np.random.default_rng(3)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([1.0, -0.5, 2.0]).as_matrix(), [0.01, 0.02, 0.5])
    scene, cls = _scene_with_object(obj, T)
    runs = []
    for beside in (True, False):
        monkeypatch.setattr(mle_mod, "FINISH_BESIDE_CERTIFIER", beside)
        runs.append(estimate_mle(scene, cls, obj, params=MLEParams(num_rotations=128), rng=0))
    a, b = runs
    assert a.certificate is not None
    assert ("eq2_certified_pose" in a.timings) == moved == ("eq2_certified_pose" in b.timings)
    np.testing.assert_array_equal(a.T_scene_object, b.T_scene_object)
    assert (a.log_likelihood, a.hypothesis, a.num_evaluations) == (
        b.log_likelihood, b.hypothesis, b.num_evaluations)
    assert [m.to_dict() for m in a.modes] == [m.to_dict() for m in b.modes]
    assert [(h.source, h.score) for h in a.hypotheses] == [(h.source, h.score) for h in b.hypotheses]
    assert any(h.source == "eq2" for h in a.hypotheses) == moved


def test_estimate_mle_records_its_hypotheses():
    rng = np.random.default_rng(3)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([1.0, -0.5, 2.0]).as_matrix(), [0.01, 0.02, 0.5])
    scene, cls = _scene_with_object(obj, T)
    res = estimate_mle(scene, cls, obj, params=MLEParams(certify=False, num_rotations=128), rng=0)
    # The coarse search's leading hypotheses go on as their own eq. (2) minimisers.
    sources = [h.source for h in res.hypotheses]
    assert any(s.startswith("eq2:") for s in sources), sources
    assert all(s.split(":")[0] in ("eq2", "coarse") and s.split(":")[1].isdigit()
               for s in sources), sources
    lik = PoseLikelihood(scene, cls, obj)
    for h in res.hypotheses:
        assert h.score == pytest.approx(float(lik(h.pose)), abs=1e-6)
    # The polished winner is at least as good as every refined hypothesis.
    assert res.log_likelihood >= max(h.score for h in res.hypotheses) - 1e-9


def test_search_on_a_subsample_reports_the_exact_likelihood():
    # The search climbs on 60 of the 240 points; everything reported is eq. (1) of all 240.
    rng = np.random.default_rng(3)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([1.0, -0.5, 2.0]).as_matrix(), [0.01, 0.02, 0.5])
    scene, cls = _scene_with_object(obj, T)
    lik = PoseLikelihood(scene, cls, obj)
    res = estimate_mle(scene, cls, obj, params=MLEParams(certify=False, num_rotations=128,
                                                          search_points=60), rng=0)
    assert len(obj) == 240 and res.success
    assert res.log_likelihood == pytest.approx(float(lik(res.T_scene_object)), abs=1e-6)
    assert res.log_likelihood >= lik(T) - 1.0
    assert rotation_error_deg(res.T_scene_object[:3, :3], T[:3, :3]) < 5.0
    assert np.linalg.norm(res.T_scene_object[:3, 3] - T[:3, 3]) < 0.005
    for h in res.hypotheses:
        assert h.score == pytest.approx(float(lik(h.pose)), abs=1e-6)
    for m in res.modes:
        assert m.log_likelihood == pytest.approx(float(lik(m.T_scene_object)), abs=1e-6)
    assert res.modes[0].log_likelihood == pytest.approx(res.log_likelihood)
    assert res.eq2_log_likelihood == pytest.approx(float(lik(res.eq2_result.T_target_source)))
    assert "refine_exact" in res.timings
    whole = estimate_mle(scene, cls, obj, params=MLEParams(certify=False, num_rotations=128,
                                                            search_points=None), rng=0)
    assert "refine_exact" not in whole.timings
    assert whole.log_likelihood == pytest.approx(float(lik(whole.T_scene_object)), abs=1e-6)


@pytest.mark.slow
def test_certificate_says_what_it_covers():
    from dataclasses import replace

    rng = np.random.default_rng(3)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([1.0, -0.5, 2.0]).as_matrix(), [0.01, 0.02, 0.5])
    scene, cls = _scene_with_object(obj, T)
    res = estimate_mle(scene, cls, obj, params=MLEParams(num_rotations=128), rng=0)
    assert res.certificate is not None and res.eq2_result is not None
    scope = res.certificate_scope()
    assert res.certificate.problem in scope
    # The returned pose was refined on eq. (1): it is not the certified eq. (2) minimiser.
    assert not np.allclose(res.T_scene_object, res.eq2_result.T_target_source, atol=1e-9)
    assert not res.pose_is_certified
    if res.certificate.certified:
        assert "CERTIFIED" in scope and "NOT the returned pose" in scope
    else:
        assert "CERTIFIED" not in scope and "no pose is certified" in scope
        # The bound in the certificate's own numbers: how far above the optimum the cost can be.
        c = res.certificate
        assert f"its cost {c.upper_bound:.6g} at most {c.upper_bound - c.lower_bound:.4g} above" in scope
    at_eq2 = replace(res, T_scene_object=res.eq2_result.T_target_source)
    assert at_eq2.pose_is_certified == res.certificate.certified
    assert ("covers the returned pose" in at_eq2.certificate_scope()) == res.certificate.certified
    uncertified = estimate_mle(scene, cls, obj, params=MLEParams(certify=False, num_rotations=64),
                               rng=0)
    assert not uncertified.pose_is_certified
    assert uncertified.certificate_scope().startswith("no certificate")


def test_ties_of_a_symmetric_box_are_reported_as_modes():
    # Equal descriptors on a 4 x 3 x 2 cm box: its 180-degree turns about the axes tie on eq. (1).
    size = np.array([0.04, 0.03, 0.02])
    faces = []
    for axis in range(3):  # a grid on each face, symmetric about the centre
        u, v = [np.linspace(-0.5, 0.5, int(round(size[a] / 0.004)) + 1) * size[a]
                for a in range(3) if a != axis]
        uu, vv = np.meshgrid(u, v, indexing="ij")
        for sign in (-0.5, 0.5):
            f = np.zeros((uu.size, 3))
            f[:, [a for a in range(3) if a != axis]] = np.c_[uu.ravel(), vv.ravel()]
            f[:, axis] = sign * size[axis]
            faces.append(f)
    pts = np.unique(np.round(np.concatenate(faces), 9), axis=0)
    obj = ObjectModel(pts, np.tile(np.eye(6)[0], (len(pts), 1)))
    T = make_transform(Rotation.from_rotvec([0.3, -0.2, 0.4]).as_matrix(), [0.0, 0.01, 0.5])
    scene, cls = _scene_with_object(obj, T)
    res = estimate_mle(scene, cls, obj, params=MLEParams(certify=False, num_rotations=128,
                                                          mode_window=5.0), rng=0)
    assert len(res.modes) >= 2
    assert res.modes[0].log_likelihood == pytest.approx(res.log_likelihood)
    assert all(res.log_likelihood - m.log_likelihood <= 5.0 for m in res.modes)
    assert any(m.rotation_from_best_deg > 150.0 for m in res.modes[1:])
    assert "modes within" in res.message
    off = estimate_mle(scene, cls, obj, params=MLEParams(certify=False, num_rotations=128,
                                                          explore_modes=False), rng=0)
    assert len(off.modes) == 1



def test_wide_eq2_keeps_the_right_voxels_on_a_real_frame():
    """Issue 10: at the true pose, the wide eq. (2)'s candidates hold the right voxel for enough
    object points that the truth is a consistent set no random rotation matches."""
    from certpose.estimation.pipeline import PoseParams
    from certpose.geometry.features import FPFHBackbone
    from certpose.geometry.objects import object_from_points
    from certpose.io.ycbv import load_model_points, load_ycbv_frame
    from certpose.model.classifier import classify_from_mask
    from certpose.model.scene import build_scene_field
    from tests.conftest import require_data

    require_data("ycbv", "0002")
    root = require_data("ycbv")
    name = "006_mustard_bottle"
    params = PoseParams()
    yf = load_ycbv_frame(root, "0002/000001")
    mask = yf.object_mask(name)
    backbone = FPFHBackbone()
    scene = build_scene_field(yf.frame, backbone, voxel_size=params.voxel_size, roi_mask=mask,
                              margin=params.roi_margin)
    obj = object_from_points(load_model_points(root / "models" / name / "points.xyz"), backbone,
                             voxel_size=params.voxel_size, name=name)
    cls = classify_from_mask(scene, yf.frame.with_mask(mask), params=params.classifier)
    T = yf.poses[name]  # scene = camera frame

    def points_with_an_inlier(eq2, R, t):
        ok = eq2.problem.residuals_sq(R, t) <= eq2.problem.cbar2
        return int(np.unique(eq2.object_index[ok]).size)

    eq2 = build_eq2_problem(scene, cls, obj, params=WIDE_EQ2, rng=0)
    assert eq2.problem.n == WIDE_EQ2.num_object_points * WIDE_EQ2.top_k
    at_truth = points_with_an_inlier(eq2, T[:3, :3], T[:3, 3])
    assert at_truth >= 8
    # No random rotation about the object's true centre gathers as many.
    centre = T[:3, :3] @ obj.centroid + T[:3, 3]
    rand = [points_with_an_inlier(eq2, R, centre - R @ obj.centroid)
            for R in Rotation.random(200, random_state=0).as_matrix()]
    assert max(rand) < at_truth
    # The defaults (40 x top-4, certifiable) keep the right voxel for far fewer points.
    default = build_eq2_problem(scene, cls, obj, params=Eq2Params(), rng=0)
    assert default.problem.n == 160
    assert points_with_an_inlier(default, T[:3, :3], T[:3, 3]) < at_truth / 2


def test_evidence_centres_ignore_far_outliers_and_merge_fragments():
    from certpose.estimation.mle import evidence_centres
    from certpose.model.grid import VOXEL_CENTRE_OFFSET, GridSpec

    grid = GridSpec(np.zeros(3), 0.01, (120, 40, 40), VOXEL_CENTRE_OFFSET)
    pos = np.zeros(grid.shape, dtype=bool)
    # An object split in two by an occluder (a 2-voxel gap), and a few bled-over voxels 80 cm
    # behind it: the mean of all positives lands 10 cm off the object.
    pos[10:16, 10:16, 10:16] = True
    pos[18:24, 10:16, 10:16] = True
    pos[100:105, 30:35, 30:35] = True
    idx = np.argwhere(pos)
    obj = idx[idx[:, 0] < 50]
    true_centre = grid.centres(obj).mean(axis=0)
    assert np.linalg.norm(grid.centres(idx).mean(axis=0) - true_centre) > 0.05
    centres = evidence_centres(pos, grid, radius=0.08)
    assert centres.shape == (2, 3)
    np.testing.assert_allclose(centres[0], true_centre, atol=1e-9)  # both fragments, one centre
    np.testing.assert_allclose(centres[1], grid.centres(idx[idx[:, 0] >= 50]).mean(axis=0))
    assert evidence_centres(pos, grid, radius=0.08, max_centres=1).shape == (1, 3)
    # With a small radius the fragments are separate centres, the larger first.
    pos[18:24, 10:16, 10:13] = False
    small = evidence_centres(pos, grid, radius=0.02, max_centres=3)
    assert small.shape == (3, 3) and small[0][0] < small[1][0]
    assert evidence_centres(np.zeros(grid.shape, bool), grid, radius=0.08).shape == (0, 3)
    with pytest.raises(ValueError, match="positive"):
        evidence_centres(pos[0], grid, radius=0.08)
    with pytest.raises(ValueError, match="radius"):
        evidence_centres(pos, grid, radius=0.0)
    with pytest.raises(ValueError, match="max_centres"):
        evidence_centres(pos, grid, radius=0.08, max_centres=0)


def test_polishing_several_poses_together_gives_each_its_own_climb():
    """The MLE polishes the modes just outside its window in one batch (``mle._polish_all``):
    each pose must end where its own compass search, run alone, ends, to the bit."""
    from certpose.estimation.batch import polish_poses
    from certpose.estimation.mle import Hypothesis, MLEParams, _polish_all, _Search

    obj, T, scene, cls, lik = _box_case([0.4, -0.3, 0.2], [0.0, 0.01, 0.5])
    starts = np.stack([T @ make_transform(Rotation.from_rotvec(np.radians(d) * np.asarray(a)).as_matrix(), t)
                       for d, a, t in ((3, [1.0, 0, 0], [0.003, 0, 0]), (5, [0, 0, 1.0], [0, -0.002, 0.002]),
                                       (0, [1.0, 0, 0], [0, 0, 0]), (8, [0, 1.0, 0], [0.004, 0.0, -0.003]))])
    search = _Search(lik, lik, lik, obj, 0.03, MLEParams())
    hyps = [Hypothesis(P, float(lik(P)), f"turn:{k}") for k, P in enumerate(starts)]
    together = _polish_all(search, hyps)
    for h, got in zip(hyps, together, strict=True):
        (P1,), (v1,), _ = polish_poses(lik, h.pose, scale=0.03)
        np.testing.assert_array_equal(got.pose, P1)
        assert got.score == v1 and got.source == h.source and got.score >= h.score
    assert len({round(h.score, 6) for h in together}) > 1
    assert search.n_eval > 4 and search.timings["polish"] > 0


def test_compass_polish_climbs_to_the_top_and_never_worsens():
    from certpose.estimation.batch import polish_poses

    obj, T, scene, cls, lik = _box_case([0.4, -0.3, 0.2], [0.0, 0.01, 0.5])
    # Two starts a few millimetres and degrees off the truth, and the truth's refined top.
    off = np.stack([T @ make_transform(Rotation.from_rotvec(np.radians(3) * np.asarray(a)).as_matrix(),
                                       t) for a, t in (([1.0, 0, 0], [0.003, 0, 0]),
                                                       ([0, 0, 1.0], [0, -0.002, 0.002]))])
    v0 = lik(off)
    P, v, n = polish_poses(lik, off, scale=0.03)
    assert P.shape == (2, 4, 4) and v.shape == (2,) and n > 2
    np.testing.assert_allclose(v, lik(P), rtol=1e-9)
    assert np.all(v > v0 + 1.0)  # climbed
    assert np.all(v >= lik(T) - 2.0)  # to the truth's top (within the piecewise-linear kinks)
    # (eq. (1)'s top on this 4 mm grid lies about 2 degrees from the truth, 3 nats above it)
    assert all(rotation_error_deg(p[:3, :3], T[:3, :3]) < 4.0 for p in P)
    # From the top it stays (the values never fall); one pose in, one out.
    P1, v1, _ = polish_poses(lik, P[0], scale=0.03)
    assert P1.shape == (1, 4, 4) and v1[0] >= v[0]
    with pytest.raises(ValueError, match="T0"):
        polish_poses(lik, np.eye(3), scale=0.03)
    with pytest.raises(ValueError, match="scale"):
        polish_poses(lik, T, scale=0.0)


def test_compass_polish_on_chosen_axes_holds_the_others():
    from certpose.estimation.batch import polish_poses

    obj, T, scene, cls, lik = _box_case([0.4, -0.3, 0.2], [0.0, 0.01, 0.5])
    off = T @ make_transform(Rotation.from_rotvec(np.radians([3.0, 0.0, 0.0])).as_matrix(), [0.003, 0, 0])
    # Translations only: the rotation stays as it started, the value still climbs.
    moves = np.hstack([np.eye(3), np.zeros((3, 3))])
    (P,), (v,), n = polish_poses(lik, off, scale=0.03, axes=np.vstack([moves, -moves]))
    np.testing.assert_allclose(P[:3, :3], off[:3, :3], atol=1e-12)
    assert v > float(lik(off)) and n > 6
    # All twelve directions climb at least as high as the translations alone here.
    (_,), (v_all,), _ = polish_poses(lik, off, scale=0.03)
    assert v_all > v
    for bad in (np.zeros((0, 6)), np.ones((2, 5)), np.full((1, 6), np.nan)):
        with pytest.raises(ValueError, match="axes"):
            polish_poses(lik, off, scale=0.03, axes=bad)
    with pytest.raises(ValueError, match="min_step"):
        polish_poses(lik, T, scale=0.03, step=1e-3, min_step=1e-2)
    with pytest.raises(ValueError, match="polish"):
        MLEParams(polish="nelder-mead")

def test_basin_hop_climbs_out_of_a_local_maximum_and_never_worsens():
    from certpose.estimation.batch import basin_hop, refine_poses

    # The ungraded free space: every free voxel pays c_empty, so that the local maximum below
    # lies far below the truth (the graded default forgives the first 5-10 mm of it).
    obj, T, scene, cls, lik = _box_case([0.4, -0.3, 0.2], [0.0, 0.01, 0.5], seed=7,
                                        params=_UNGRADED_FREE_SPACE)
    # Starts 60 degrees off: local refinement stalls hundreds of nats below the truth.
    starts = np.stack([T @ make_transform(Rotation.from_rotvec(np.radians(60) * np.asarray(a)).as_matrix(),
                                          [0.004, 0, 0]) for a in ([1.0, 0, 0], [0, 1.0, 0])])
    local, v_local = refine_poses(lik, starts, scale=0.03)
    assert np.all(v_local < lik(T) - 100.0)
    hopped, v = basin_hop(lik, local, scale=0.03, rounds=4, samples=24, rotation_deg=10.0, rng=0)
    assert hopped.shape == (2, 4, 4) and v.shape == (2,)
    np.testing.assert_allclose(v, lik(hopped), rtol=1e-9)
    assert np.all(v >= lik(T) - 5.0)  # both back in the truth's basin
    assert all(rotation_error_deg(h[:3, :3], T[:3, :3]) < 5.0 for h in hopped)
    # The coarse stage (a subsample) only preselects: values are still on the exact eq. (1).
    coarse = PoseLikelihood(scene, cls, obj.subsample(40, rng=0), params=lik.params)
    h1, v1 = basin_hop(lik, local[0], scale=0.03, coarse_likelihood=coarse, rounds=2, rng=1)
    assert h1.shape == (1, 4, 4) and v1[0] == pytest.approx(float(lik(h1[0]))) and v1[0] >= v_local[0]
    # No rounds: the starts come back.
    h0, v0 = basin_hop(lik, local, scale=0.03, rounds=0)
    np.testing.assert_array_equal(h0, local)
    with pytest.raises(ValueError, match="T0"):
        basin_hop(lik, np.eye(3), scale=0.03)
    with pytest.raises(ValueError, match="scale"):
        basin_hop(lik, T, scale=-1.0)
    with pytest.raises(ValueError, match="samples"):
        basin_hop(lik, T, scale=0.03, samples=0)
    with pytest.raises(ValueError, match="rotation_deg"):
        basin_hop(lik, T, scale=0.03, rotation_deg=-1.0)
    with pytest.raises(ValueError, match="drop_behind"):
        basin_hop(lik, T, scale=0.03, drop_behind=-1.0)


def test_basin_hop_refines_a_pose_once_however_many_samples_climb_onto_it():
    from certpose.estimation.batch import basin_hop, refine_poses

    obj, T, scene, cls, lik = _box_case([0.4, -0.3, 0.2], [0.0, 0.01, 0.5], seed=7,
                                        params=_UNGRADED_FREE_SPACE)
    coarse = PoseLikelihood(scene, cls, obj.subsample(40, rng=0), params=lik.params)
    start = T @ make_transform(Rotation.from_rotvec([0.0, np.radians(60), 0.0]).as_matrix(),
                               [0.004, 0, 0])
    local, v_local = refine_poses(lik, start[None], scale=0.03)
    n_eval = [0]

    def counted(P):
        n_eval[0] += len(P)  # (N, 4, 4) poses
        return lik(P)

    kw = dict(scale=0.03, coarse_likelihood=coarse, rounds=2, samples=24, rotation_deg=10.0,
              rng=1)
    every, v_every = basin_hop(counted, local, merge=None, **kw)
    n_every, n_eval[0] = n_eval[0], 0
    once, v_once = basin_hop(counted, local, **kw)
    # Fewer exact evaluations, out of the local maximum all the same (hundreds of nats), and
    # the value is the pose's.
    assert n_eval[0] < n_every
    assert v_once[0] >= lik(T) - 5.0 and v_every[0] >= lik(T) - 5.0  # the truth's basin
    assert v_once[0] == pytest.approx(float(lik(once[0])), rel=1e-12)


def test_basin_hop_drops_a_start_far_behind_and_keeps_the_others_path():
    from certpose.estimation.batch import basin_hop, refine_poses

    obj, T, scene, cls, lik = _box_case([0.4, -0.3, 0.2], [0.0, 0.01, 0.5], seed=7,
                                        params=_UNGRADED_FREE_SPACE)
    # One start near the truth, one 90 degrees off (hundreds of nats behind, and still so
    # after a round).
    starts = np.stack([T @ make_transform(Rotation.from_rotvec(np.radians(a) * np.array([1.0, 0, 0])).as_matrix(),
                                          [0.002, 0, 0]) for a in (3.0, 90.0)])
    local, v_local = refine_poses(lik, starts, scale=0.03)
    assert v_local[1] < v_local[0] - 100.0
    kw = dict(scale=0.03, rounds=3, samples=8, rotation_deg=10.0, rng=0)
    full, v_full = basin_hop(lik, local, **kw)
    cut, v_cut = basin_hop(lik, local, drop_behind=50.0, **kw)
    # The leading start draws the same perturbations and ends where it ended without the cut.
    np.testing.assert_array_equal(cut[0], full[0])
    assert v_cut[0] == v_full[0]
    # The trailing one stopped after the first round: never below its start, short of the
    # uncut search (which climbs on), and its value is its pose's.
    assert v_local[1] <= v_cut[1] < v_full[1]
    assert v_cut[1] == pytest.approx(float(lik(cut[1])), rel=1e-12)
    first, v_first = basin_hop(lik, local, **{**kw, "rounds": 1})
    np.testing.assert_array_equal(cut[1], first[1])


def _turned_box_starts(angles):
    """A box's likelihood and starts turned by ``angles`` (deg) about its y axis, 3 mm off."""
    rng = np.random.default_rng(7)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([0.4, -0.3, 0.2]).as_matrix(), [0.0, 0.01, 0.5])
    scene, cls = _scene_with_object(obj, T)
    turn = [make_transform(Rotation.from_rotvec(np.radians(a) * np.array([0, 1.0, 0])).as_matrix(),
                           [0.003, 0, 0]) for a in angles]
    return PoseLikelihood(scene, cls, obj), np.stack([T @ D for D in turn])


def test_refine_poses_merge_climbs_onto_one_pose_once():
    from certpose.estimation.batch import refine_poses

    # Two starts 0.2 degrees apart (one basin, one climb) and one 90 degrees off.
    lik, starts = _turned_box_starts((4.0, 4.2, 90.0))
    n_eval = [0]

    def counted(P):
        n_eval[0] += len(P)  # (N, 4, 4) poses
        return lik(P)

    kw = dict(scale=0.03, max_iter=40)
    free, v_free = refine_poses(counted, starts, **kw)
    n_free, n_eval[0] = n_eval[0], 0
    merged, v_merged = refine_poses(counted, starts, merge=0.01, **kw)
    assert n_eval[0] < n_free
    # The near pair: the better climbs as it does alone, the other stopped below where it
    # climbs alone; the far start climbs as without the merging.
    i = int(np.argmax(v_merged[:2]))
    alone, v_alone = refine_poses(lik, starts[[i]], **kw)
    np.testing.assert_array_equal(merged[i], alone[0])
    assert v_merged[i] == v_alone[0]
    assert lik(starts[1 - i]) <= v_merged[1 - i] < v_free[1 - i]
    assert v_merged[1 - i] == pytest.approx(float(lik(merged[1 - i])), rel=1e-12)
    np.testing.assert_array_equal(merged[2], free[2])
    # Poses of different groups never merge.
    apart, _ = refine_poses(lik, starts, merge=0.01, groups=[0, 1, 2], **kw)
    np.testing.assert_array_equal(apart, free)
    with pytest.raises(ValueError, match="merge"):
        refine_poses(lik, starts, scale=0.03, merge=-1.0)
    with pytest.raises(ValueError, match="groups"):
        refine_poses(lik, starts, scale=0.03, merge=0.01, groups=[0, 1])


def test_refine_poses_prune_stops_the_trailing_hypotheses():
    from certpose.estimation.batch import refine_poses

    lik, starts = _turned_box_starts((4.0, 90.0))
    kw = dict(scale=0.03, max_iter=40)
    free, v_free = refine_poses(lik, starts, **kw)
    alone, v_alone = refine_poses(lik, starts[:1], **kw)
    # The leader climbs as it does alone, whatever happens to the other.
    both, v_both = refine_poses(lik, starts, prune_margin=0.0, **kw)
    np.testing.assert_array_equal(both[0], alone[0])
    assert v_both[0] == v_alone[0]
    # The one far behind is stopped early: below where it climbs without the pruning, and
    # never below its start.
    assert v_free[1] < v_free[0] - 50.0
    assert lik(starts[1]) <= v_both[1] < v_free[1]
    assert v_both[1] == pytest.approx(float(lik(both[1])), rel=1e-12)
    # A generous margin prunes nothing.
    kept, v_kept = refine_poses(lik, starts, prune_margin=1e6, **kw)
    np.testing.assert_array_equal(kept, free)
    with pytest.raises(ValueError, match="prune_margin"):
        refine_poses(lik, starts, scale=0.03, prune_margin=-1.0)
    with pytest.raises(ValueError, match="prune_every"):
        refine_poses(lik, starts, scale=0.03, prune_margin=1.0, prune_every=2)


def _ycbv_mle_case(frame, name):
    """One YCB-Video pair as ``certpose pose`` prepares it (geometry-only model, mask
    classifier): the setup, the true pose, eq. (1) at the locally refined truth, the MLE (rng 0)
    and the parameters. Skips without the frame's scene."""
    from certpose.estimation.pipeline import PoseParams, ycbv_setup
    from tests.conftest import require_data

    require_data("ycbv", frame.split("/")[0])
    params = PoseParams()
    setup = ycbv_setup(require_data("ycbv"), frame, name, params=params)
    scene, cls, obj = setup.scene, setup.classification, setup.object_model
    T_gt = setup.frame.poses[name].astype(np.float64)
    lik = PoseLikelihood(scene, cls, obj, params=params.likelihood or LikelihoodParams())
    _, ll_ref, _ = refine_pose(lik, T_gt, scale=obj.radius)
    res = estimate_mle(scene, cls, obj, params=params.mle, likelihood_params=params.likelihood,
                       viewpoint=setup.frame.frame.T_world_camera[:3, 3], rng=0)
    return setup, T_gt, ll_ref, res, params

@pytest.mark.slow
def test_the_search_finds_the_can_that_a_bleeding_mask_pulled_away_from():
    """Issue 10 item 3 on a real frame (YCB-Video 0049/000020, tuna can): mask pixels on the far
    background put about a fifth of the classifier's positives 1.2 m behind the can. Their mean, where the
    search used to start, is 26 cm off; every pose it found hid the can in unobserved space,
    215 nats below the locally refined truth."""
    from certpose.estimation.pipeline import pose_errors
    from certpose.model.grid import scene_grid_spec

    setup, T_gt, ll_ref, res, params = _ycbv_mle_case("0049/000020", "007_tuna_fish_can")
    scene, cls, obj = setup.scene, setup.classification, setup.object_model
    true_centre = T_gt[:3, :3] @ obj.centroid + T_gt[:3, 3]
    pos = scene_grid_spec(scene).centres(np.argwhere(cls.positive))
    assert np.linalg.norm(pos.mean(axis=0) - true_centre) > 0.1  # the premise
    assert res.log_likelihood >= ll_ref - 1.0
    err = pose_errors(res.T_scene_object, T_gt, setup.model_points)
    assert err.add_s < 0.01


@pytest.mark.slow
def test_a_flip_that_ties_reports_the_truth_among_the_modes():
    """Issue 10 item 4 on a real frame (YCB-Video 0050/000010, mustard bottle, geometry-only
    model): eq. (1) prefers the bottle turned by about 180 degrees by less than the mode window
    over the locally refined truth (3.9 nats). The truth's basin must then be among the reported
    modes; on 0050/000001 its turn used to stall 6 nats below the polished winner and was left
    out (there the flip leads by 6.1 nats, beyond the window, since the models' Voronoi areas of
    2026-11-26)."""
    from certpose.estimation.pipeline import pose_errors
    from certpose.model.likelihood import PoseLikelihood
    from certpose.sampling.sampler import default_temperature

    setup, T_gt, ll_ref, res, params = _ycbv_mle_case("0050/000010", "006_mustard_bottle")
    # The window is in tempered nats: eq. (1) over the sampler's default temperature.
    lik = PoseLikelihood(setup.scene, setup.classification, setup.object_model, params=params.likelihood)
    window = params.mle.mode_window * max(1.0, default_temperature(lik, res.T_scene_object))
    assert ll_ref >= res.log_likelihood - window  # the premise: a tie
    rot = [pose_errors(m.T_scene_object, T_gt, setup.model_points).rotation_deg for m in res.modes]
    assert min(rot) < 10.0, rot
    assert all(res.log_likelihood - m.log_likelihood <= window for m in res.modes)


def _occluded_bowl(frame: str):
    """YCB-Video 0049, the bowl (partly hidden by the objects in front of it): setup, truth,
    classifier centre and a sample of its positives."""
    from certpose.estimation.mle import evidence_centres
    from certpose.estimation.pipeline import PoseParams, ycbv_setup
    from certpose.model.grid import scene_grid_spec
    from tests.conftest import require_data

    require_data("ycbv", "0049")
    name = "024_bowl"
    params = PoseParams()
    setup = ycbv_setup(require_data("ycbv"), f"0049/{frame}", name, params=params)
    grid = scene_grid_spec(setup.scene)
    obj = setup.object_model
    centre = evidence_centres(setup.classification.positive, grid, radius=obj.radius)[0]
    pos = grid.centres(np.argwhere(setup.classification.positive))
    pos = pos[np.linalg.norm(pos - centre, axis=1) < 2 * obj.radius]
    return setup, params, setup.frame.poses[name].astype(np.float64), centre, pos


@pytest.mark.slow
def test_the_coarse_search_reaches_a_partly_occluded_object():
    """Issue 10 item 3 (YCB-Video 0049/000010, bowl): the seen part's centroid is 4 cm from that
    of the bowl's camera-facing side, where the coarse search put each rotation before its
    +-0.15-radius offsets (1.3 cm): no coarse pose near the truth was among the leading ones and
    the MLE ended 123 nats below the refined truth. Aligned to the positives, one is."""
    from certpose.estimation.mle import _distinct_top

    setup, params, T_gt, centre, pos = _occluded_bowl("000010")
    obj = setup.object_model
    small = obj.subsample(128, rng=0)
    lik = PoseLikelihood(setup.scene, setup.classification, small,
                         params=replace(params.likelihood, free_space_erosion=3))
    axis = T_gt[:3, 2]  # the bowl's axis of symmetry (object z)

    def leading_near_truth(evidence):
        poses, values = coarse_search(lik, small, centre, viewing_direction=centre,
                                      evidence=evidence, rng=0)
        top = _distinct_top(poses, values, 16, 0.5 * obj.radius, math.radians(20))
        return [i for i in top
                if np.linalg.norm(poses[i, :3, 3] - T_gt[:3, 3]) < 0.015
                and math.degrees(math.acos(min(1.0, poses[i, :3, 2] @ axis))) < 25.0]

    assert not leading_near_truth(None)  # the premise: without the alignment, none
    assert leading_near_truth(pos[np.linspace(0, len(pos) - 1, 32).astype(int)])
    with pytest.raises(ValueError, match="evidence"):
        coarse_search(lik, small, centre, viewing_direction=centre, evidence=np.zeros((4, 2)))


@pytest.mark.slow
def test_the_mle_finds_the_basin_of_a_partly_occluded_object():
    """Issue 10 item 3 end to end on the same bowl: eq. (1) at the returned pose at least that
    of the locally refined truth (was 123 nats below, ADD-S 3.4 cm)."""
    from certpose.estimation.pipeline import pose_errors

    setup, params, T_gt, _, _ = _occluded_bowl("000010")
    scene, cls, obj = setup.scene, setup.classification, setup.object_model
    lik = PoseLikelihood(scene, cls, obj, params=params.likelihood or LikelihoodParams())
    _, ll_ref, _ = refine_pose(lik, T_gt, scale=obj.radius)
    res = estimate_mle(scene, cls, obj, params=params.mle, likelihood_params=params.likelihood,
                       viewpoint=setup.frame.frame.T_world_camera[:3, 3], rng=0)
    assert res.log_likelihood >= ll_ref - 1.0
    assert pose_errors(res.T_scene_object, T_gt, setup.model_points).add_s < 0.01


def test_seeded_eq2_keeps_the_pairs_near_the_seeds():
    """Candidates by proximity: every pair lies within the radius under some seed, at most
    ``seed_neighbors`` per object point and seed, each pair once; with the true pose as a seed
    every object point with a voxel within the noise bound has its inlier."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(5)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([0.4, 0.1, -0.7]).as_matrix(), [0.02, -0.01, 0.45])
    scene, cls = _scene_with_object(obj, T)
    off = T @ make_transform(Rotation.from_rotvec([0.0, 0.3, 0.0]).as_matrix(), [0.01, 0.0, 0.0])
    params = Eq2Params(seed_object_points=50, seed_neighbors=3, seed_radius=0.012)
    eq2 = build_eq2_problem(scene, cls, obj, params=params, rng=0, seeds=np.stack([T, off, T]))
    prob = eq2.problem
    pairs = np.stack([eq2.object_index, eq2.grid_index], axis=1)
    assert np.unique(pairs, axis=0).shape[0] == prob.n  # the repeated seed adds nothing
    src = obj.points[eq2.object_index]
    np.testing.assert_allclose(prob.source, src)
    near = [np.linalg.norm(src @ S[:3, :3].T + S[:3, 3] - prob.target, axis=1) for S in (T, off)]
    assert np.all(np.minimum(*near) <= params.seed_radius + 1e-12)
    counts = np.bincount(eq2.object_index)
    assert counts.max() <= 2 * params.seed_neighbors
    # The weights are still c_ij - c_floor of the pairs kept.
    np.testing.assert_allclose(prob.weights, eq2.c - eq2.c_floor)
    # At the truth: every sampled point with an occupied voxel within eps has an inlier.
    ok = prob.residuals_sq(T[:3, :3], T[:3, 3]) <= prob.cbar2
    rows = np.unique(eq2.object_index)
    d, _ = cKDTree(eq2.grid_points).query(obj.points[rows] @ T[:3, :3].T + T[:3, 3])
    has_voxel = rows[d <= prob.noise_bound.max()]
    assert has_voxel.size >= 40
    assert set(has_voxel) <= set(eq2.object_index[ok])


def test_estimate_eq2_from_an_offset_seed_lands_on_the_truth():
    from certpose.model.eq2 import estimate_eq2

    rng = np.random.default_rng(6)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([1.0, -0.5, 2.0]).as_matrix(), [0.01, 0.02, 0.5])
    scene, cls = _scene_with_object(obj, T)
    seed = T @ make_transform(Rotation.from_rotvec([0.12, 0.0, -0.08]).as_matrix(),
                              [0.008, -0.006, 0.0])
    eq2, res = estimate_eq2(scene, cls, obj, seed, params=Eq2Params(seed_object_points=60),
                            rng=0)
    assert res.success and res.info["certificate_message"] == "not requested"
    # A 4 x 3 x 2 cm box on 5 mm voxels: a voxel at its corners is 10-15 degrees.
    assert rotation_error_deg(res.rotation, T[:3, :3]) < 5.0
    assert np.linalg.norm(res.translation - T[:3, 3]) < 0.004
    assert rotation_error_deg(seed[:3, :3], T[:3, :3]) > 8.0
    # The problem returned is the last local round's: candidates within two noise bounds of the
    # round before's minimiser, which the last round moved by well under a millimetre or two.
    moved = eq2.problem.source @ res.rotation.T + res.translation
    assert np.all(np.linalg.norm(moved - eq2.problem.target, axis=1) <= 2 * 0.005 + 0.002)
    assert eq2.problem.n <= 60 * 8


def test_seeded_eq2_local_rounds_from_a_start_pose_register_there():
    """The local rounds begun at ``start`` (the MLE passes the minimiser once refined on eq. (1))
    end next to ``start``, not at the seed's own minimiser; a ``start`` near no voxel, or no
    rounds at all, leave the seed's minimiser and problem as they were."""
    from certpose.model.eq2 import solve_eq2_about_seeds

    rng = np.random.default_rng(8)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([0.3, -0.6, 1.1]).as_matrix(), [0.0, 0.01, 0.5])
    scene, cls = _scene_with_object(obj, T)
    # A seed turned by 90 degrees about the box's shortest axis: its minimiser stays turned.
    turned = T @ make_transform(Rotation.from_rotvec([0.0, 0.0, math.pi / 2]).as_matrix(),
                                np.zeros(3))
    seeded = solve_eq2_about_seeds(scene, cls, obj, turned[None], rng=0,
                                   params=Eq2Params(seed_object_points=60))
    assert rotation_error_deg(seeded.results[0].rotation, T[:3, :3]) > 45.0
    start = T @ make_transform(Rotation.from_rotvec([0.05, -0.04, 0.0]).as_matrix(),
                               [0.003, -0.002, 0.001])
    eq2, res = seeded.local_rounds(0, start)
    assert rotation_error_deg(res.rotation, T[:3, :3]) < 3.0
    assert np.linalg.norm(res.translation - T[:3, 3]) < 0.002
    # Its problem is the last round's: the voxels within two noise bounds of the pose before.
    moved = eq2.problem.source @ res.rotation.T + res.translation
    assert np.all(np.linalg.norm(moved - eq2.problem.target, axis=1) <= 2 * 0.005 + 0.002)
    # From nowhere near a voxel, and without rounds: the seed's minimiser, unchanged.
    far = make_transform(np.eye(3), [1.0, 0.0, 0.5])
    eq2_far, res_far = seeded.local_rounds(0, far)
    assert res_far is seeded.results[0] and eq2_far is seeded.problems[0]
    none = solve_eq2_about_seeds(scene, cls, obj, turned[None], rng=0,
                                 params=Eq2Params(seed_object_points=60, local_rounds=0))
    assert none.local_rounds(0, start)[1] is none.results[0]
    with pytest.raises(ValueError, match="start"):
        seeded.local_rounds(0, np.stack([start, start]))


def test_seeded_eq2_solves_the_further_seeds_with_gnc_alone():
    """``gnc_seeds``: the seeds after the first ``num_seeds`` are solved too (GNC without the
    max-clique pruning), each minimiser next to its own seed."""
    from certpose.model.eq2 import solve_eq2_about_seeds

    rng = np.random.default_rng(9)
    obj = _box_object(rng)
    T = make_transform(Rotation.from_rotvec([-0.7, 0.2, 0.4]).as_matrix(), [0.01, 0.0, 0.5])
    scene, cls = _scene_with_object(obj, T)
    small = make_transform(Rotation.from_rotvec([0.06, 0.0, -0.05]).as_matrix(),
                           [0.004, 0.0, -0.003])
    other = make_transform(Rotation.from_rotvec([0.0, -0.05, 0.04]).as_matrix(),
                           [-0.002, 0.003, 0.0])
    seeds = np.stack([T @ small, T @ other, T @ np.linalg.inv(small), T @ np.linalg.inv(other)])
    params = Eq2Params(seed_object_points=60, num_seeds=1, gnc_seeds=2)
    seeded = solve_eq2_about_seeds(scene, cls, obj, seeds, params=params, rng=0)
    np.testing.assert_array_equal(seeded.seed_rows, [0, 1, 2])  # the 4th is beyond both
    assert "clique" not in seeded.results[1].solver and "clique" not in seeded.results[2].solver
    for res in seeded.results:
        assert rotation_error_deg(res.rotation, T[:3, :3]) < 5.0
        assert np.linalg.norm(res.translation - T[:3, 3]) < 0.004
    only = solve_eq2_about_seeds(scene, cls, obj, seeds, params=replace(params, gnc_seeds=0),
                                 rng=0)
    np.testing.assert_array_equal(only.seed_rows, [0])


def test_seeded_eq2_rejects_bad_seeds_and_params():
    from certpose.model.eq2 import estimate_eq2

    rng = np.random.default_rng(7)
    obj = _box_object(rng)
    T = make_transform(np.eye(3), [0.0, 0.0, 0.5])
    scene, cls = _scene_with_object(obj, T)
    with pytest.raises(ValueError, match=r"`seeds` to have shape \(S, 4, 4\)"):
        build_eq2_problem(scene, cls, obj, seeds=np.eye(3))
    with pytest.raises(ValueError, match="last row of `seeds`"):
        build_eq2_problem(scene, cls, obj, seeds=np.zeros((2, 4, 4)))
    far = make_transform(np.eye(3), [1.0, 0.0, 0.5])
    with pytest.raises(ValueError, match="seed pose"):
        estimate_eq2(scene, cls, obj, far)
    for kwargs, name in (({"num_seeds": -1}, "num_seeds"), ({"seed_object_points": 2},
                         "seed_object_points"), ({"seed_neighbors": 0}, "seed_neighbors"),
                         ({"seed_radius": 0.0}, "seed_radius"), ({"local_rounds": -1},
                         "local_rounds"), ({"gnc_seeds": -1}, "gnc_seeds")):
        with pytest.raises(ValueError, match=name):
            Eq2Params(**kwargs)


@pytest.mark.slow
def test_seeded_eq2_keeps_the_right_voxels_across_scenes():
    """Issue 10 item 2: the potted-meat can in 0049/000001, appearance model built from scene
    0002 (never from 0049), mask classifier. Eq. (2) with the pairs near the coarse eq. (1)
    search's leading distinct poses (as the MLE builds it) holds the right voxel at the true pose
    for many object points (measured 18 of 100); the descriptors' top-4 of 40 points (main's
    eq. (2) before) held it for at most 1. The MLE's raw eq. (2) pose is within 1 cm ADD-S. (On
    the voxel-averaged model these counts were measured on; the surface-sampled model that
    ``build_ycbv_object_model`` builds by default holds the right voxel for 5 points, its raw
    eq. (2) pose within 1 cm ADD-S all the same: examples/benchmarks/bench_box.py.)"""
    from certpose.estimation.pipeline import (
        PoseParams,
        _scene_for,
        build_ycbv_object_model,
        likelihood_params_for,
        pose_errors,
    )
    from certpose.io.ycbv import load_model_points, load_ycbv_frame
    from certpose.model.classifier import classify_from_mask
    from tests.conftest import require_data

    require_data("ycbv", "0049")
    root = require_data("ycbv")
    name = "010_potted_meat_can"
    built = build_ycbv_object_model(root, ["0002/000001", "0002/000010", "0002/000020"], name,
                                    sampling="voxel")
    assert "0049" not in built.scenes
    params = PoseParams()
    yf = load_ycbv_frame(root, "0049/000001")
    mask = yf.object_mask(name)
    scene = _scene_for(yf.frame, mask, params, built.backbone)
    cls = classify_from_mask(scene, yf.frame.with_mask(mask), params=params.classifier)
    lp = likelihood_params_for(params.likelihood, scene.backbone)
    T = yf.poses[name]  # scene = camera frame
    obj = built.model

    def points_with_an_inlier(eq2):
        ok = eq2.problem.residuals_sq(T[:3, :3], T[:3, 3]) <= eq2.problem.cbar2
        return int(np.unique(eq2.object_index[ok]).size)

    # The coarse search's 8 best poses at least 20 degrees apart.
    centre = np.argwhere(cls.positive).mean(axis=0)
    from certpose.model.grid import scene_grid_spec

    centre = scene_grid_spec(scene).centres(np.rint(centre[None]).astype(int))[0]
    lik = PoseLikelihood(scene, cls, obj.subsample(128, rng=0), params=lp)
    poses, values = coarse_search(lik, obj, centre, viewing_direction=centre, rng=0)
    seeds: list[np.ndarray] = []
    for i in np.argsort(-values):
        if all(rotation_error_deg(poses[i][:3, :3], S[:3, :3]) > 20.0 for S in seeds):
            seeds.append(poses[i])
        if len(seeds) == 8:
            break
    seeded = build_eq2_problem(scene, cls, obj, likelihood_params=lp, rng=0, seeds=np.stack(seeds))
    assert points_with_an_inlier(seeded) >= 10
    descriptor = build_eq2_problem(scene, cls, obj, params=Eq2Params(), likelihood_params=lp,
                                   rng=0)
    assert points_with_an_inlier(descriptor) < points_with_an_inlier(seeded) / 3
    res = estimate_mle(scene, cls, obj, params=MLEParams(certify=False, hop_rounds=0,
                                                         explore_modes=False),
                       likelihood_params=lp, rng=0)
    err = pose_errors(res.eq2_result.T_target_source, T,
                      load_model_points(root / "models" / name / "points.xyz"))
    assert err.add_s <= 0.01


def test_translation_alignment_rows_are_independent_and_reach_the_seen_face():
    """_align_translations slides each rotation's translation on its own (the distances are
    computed 64 rotations at a time: 100 rows cross a block's edge): every row equals the row
    aligned alone, and the seen face of a box, started 1 cm off, is reached."""
    from certpose.estimation.mle import _align_translations

    rng = np.random.default_rng(3)
    size = np.array([0.08, 0.05, 0.03])
    P = box_surface(rng, size, 60)
    normals = np.zeros_like(P)
    for axis in range(3):
        on = np.isclose(np.abs(P[:, axis]), size[axis] / 2)
        normals[on, axis] = np.sign(P[on, axis])
    R_true = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    t_true = np.array([0.02, -0.01, 0.6])
    view = np.array([0.0, 0.0, 1.0])  # camera at the origin, looking along +z
    R = np.stack([R_true] * 70 + list(Rotation.random(30, random_state=4).as_matrix()))
    facing = (normals @ (R.transpose(0, 2, 1) @ view).T).T < 0
    # The evidence: the true pose's facing points, as the camera sees them.
    E = (P[facing[0]] @ R_true.T + t_true)[::3]
    t0 = t_true + rng.normal(scale=0.006, size=(len(R), 3))
    t = _align_translations(R, t0, P, normals, facing, E, iterations=4, max_distance=0.05)
    alone = np.concatenate([_align_translations(R[b:b + 1], t0[b:b + 1], P, normals,
                                                facing[b:b + 1], E, iterations=4,
                                                max_distance=0.05) for b in range(len(R))])
    np.testing.assert_allclose(t, alone, rtol=0, atol=1e-12)
    assert np.abs(t0[:70] - t_true).max() > 0.01
    assert np.abs(t[:70] - t_true).max() < 2e-3


def _voxel_sampled(points: np.ndarray, voxel: float = 0.004) -> np.ndarray:
    """``points`` averaged per voxel, as object models are sampled (the axis test's tolerance
    counts median gaps of such evenly spaced samples)."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return np.asarray(cloud.voxel_down_sample(voxel).points)


def test_revolution_turns_map_a_cylinder_onto_itself_and_a_box_has_none():
    from scipy.spatial import cKDTree

    from certpose.estimation.modes import revolution_turns

    rng = np.random.default_rng(0)
    # A closed cylinder (radius 3 cm, height 10 cm) along a tilted axis through an offset point.
    th, z = rng.uniform(0, 2 * np.pi, 4000), rng.uniform(-0.05, 0.05, 4000)
    side = np.stack([0.03 * np.cos(th), 0.03 * np.sin(th), z], 1)
    r, ph = 0.03 * np.sqrt(rng.uniform(0, 1, 1000)), rng.uniform(0, 2 * np.pi, 1000)
    caps = np.stack([r * np.cos(ph), r * np.sin(ph), np.where(rng.uniform(size=1000) < 0.5, -0.05, 0.05)], 1)
    R = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    cyl = _voxel_sampled(np.vstack([side, caps]) @ R.T + [0.1, 0.02, -0.03])
    S, labels = revolution_turns(cyl, step_deg=15.0)
    assert S.shape == (47, 4, 4) and len(labels) == 47
    assert labels.count("ring-flip:0") == 1 and "ring:0" not in labels
    tree = cKDTree(cyl)
    for T in S:
        moved = cyl @ T[:3, :3].T + T[:3, 3]
        assert np.median(tree.query(moved)[0]) < 0.003
    # The flipped half really turns the cylinder over: its axis direction is reversed.
    d = R[:, 2]
    assert np.dot(S[labels.index("ring-flip:0")][:3, :3] @ d, d) < -0.99
    # A box's surface (16 x 10 x 4 cm): each point pushed onto the face of one random axis.
    half = np.array([0.08, 0.05, 0.02])
    box = rng.uniform(-1, 1, (3000, 3)) * half
    k = rng.integers(0, 3, 3000)
    box[np.arange(3000), k] = np.sign(box[np.arange(3000), k]) * half[k]
    S_box, _ = revolution_turns(_voxel_sampled(box))
    assert S_box.shape == (0, 4, 4)
    with pytest.raises(ValueError, match="step_deg"):
        revolution_turns(cyl, step_deg=0.0)


@pytest.mark.slow
def test_a_can_reports_its_ring_and_the_truth_is_on_it():
    """YCB-Video 0049/000001, tuna fish can, geometry-only model: eq. (1) cannot tell the turns
    about the can's axis apart, and the search's winner stands 122 deg from the truth. Without the
    ring no reported mode comes within 10 deg of the truth; with it one does."""
    from certpose.estimation.pipeline import PoseParams, ycbv_setup
    from tests.conftest import require_data

    require_data("ycbv", "0049")
    setup = ycbv_setup(require_data("ycbv"), "0049/000001", "007_tuna_fish_can", params=PoseParams())
    T_gt = setup.frame.poses["007_tuna_fish_can"].astype(np.float64)

    def nearest_mode_deg(ring: bool) -> tuple[float, int]:
        params = replace(PoseParams().mle, ring_modes=ring)
        res = estimate_mle(setup.scene, setup.classification, setup.object_model, params=params,
                           viewpoint=setup.frame.frame.T_world_camera[:3, 3], rng=0)
        Rs = [setup.frame.frame.T_world_camera[:3, :3].T @ m.T_scene_object[:3, :3] for m in res.modes]
        rings = sum(m.origin.startswith("ring") for m in res.modes)
        return min(Rotation.from_matrix(T_gt[:3, :3].T @ R).magnitude() for R in Rs) * 180 / np.pi, rings

    off, rings_off = nearest_mode_deg(False)
    on, rings_on = nearest_mode_deg(True)
    assert rings_off == 0 and off > 10.0
    assert rings_on >= 10 and on < 10.0
