"""The branch and bound over poses (:mod:`solvers.certify.pose_bnb`), the full problem's bound
when the maximal cliques are too many to list: sound against exhaustive enumeration of every
inlier set (the audit's families, K = 5-12), an inflated bound is caught, the certificate route
through ``certify_result(pose_search=True)``, and the real 3DMatch pair."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from solvers import solve_registration
from solvers.certificate import undiluted_gap
from solvers.certify import certify_result, pose_bnb
from solvers.certify import front as certify_front
from solvers.certify.front import _normalised
from solvers.problem import WeightedTLSProblem
from tests.test_certify_audit import FAMILIES, _rotate, audit, exact_optimum, make_family


def _outlier_cost(p: WeightedTLSProblem, R: np.ndarray, t: np.ndarray) -> float:
    return float(p.cbar2 * p.weights[p.residuals_sq(R, t) >= p.cbar2].sum())


def _violations(family: str, seeds: range, *, tol: float = 1e-3) -> tuple[list[str], int, int]:
    """Each instance's solver pose and two wrong candidates (3 and 180 deg), bounded by
    :func:`pose_bnb.pose_lower_bound`; returns the violations, the searches that completed at
    ``tol`` and the searches run."""
    bad, complete, runs = [], 0, 0
    for seed in seeds:
        rng = np.random.default_rng(7000 + 100 * FAMILIES.index(family) + seed)
        k = int(rng.integers(5, 13))
        p, _ = _normalised(make_family(rng, family, k))
        res = solve_registration(p)
        exact = exact_optimum(p)
        slack = 1e-9 * (1 + abs(exact))
        for name, R in (("solver", res.rotation), ("3deg", _rotate(res.rotation, 3.0, rng)),
                        ("180deg", _rotate(res.rotation, 180.0, rng))):
            t = res.translation
            pb = pose_bnb.pose_lower_bound(p, R, t, tol=tol, time_limit=60.0)
            runs += 1
            where = f"{family} seed {seed} K={k} {name}"
            if pb.lower > exact + slack:
                bad.append(f"{where}: lower bound {pb.lower!r} > exact minimum {exact!r}")
            if pb.upper > p.cost(R, t) + slack:
                bad.append(f"{where}: best cost {pb.upper!r} above the candidate's")
            Rb, tb = (R, t) if pb.rotation is None else (pb.rotation, pb.translation)
            if abs(p.cost(Rb, tb) - pb.upper) > slack:
                bad.append(f"{where}: the best pose's cost is not `upper`")
            if pb.complete:
                complete += 1
                gap = undiluted_gap(pb.upper, exact, _outlier_cost(p, Rb, tb))
                if gap > tol + 1e-9:
                    bad.append(f"{where}: complete, but the best pose is {gap:.3g} from the "
                               f"exact minimum")
    return bad, complete, runs


@pytest.mark.parametrize("family", FAMILIES)
def test_pose_bound_never_exceeds_the_enumerated_optimum(family: str) -> None:
    """13 families x 4 instances x 3 candidates: the bound is below the exact minimum, and a
    completed search has the exact optimum within the tolerance (a wrong candidate is
    replaced by the better pose the search finds)."""
    bad, complete, runs = _violations(family, range(4))
    assert not bad, "\n".join(bad)
    assert complete == runs  # K <= 12: every search finishes well within its minute


def test_an_inflated_bound_is_caught(monkeypatch: pytest.MonkeyPatch) -> None:
    """Mutation check: the search run on residual costs scaled by 4 (every cell's bound
    inflated) claims bounds above the enumerated minimum, which the audit reports."""
    real = pose_bnb._setup

    def inflated(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        out = real(*args, **kwargs)
        if out is None:
            return out
        kargs, *rest = out
        kargs = list(kargs)
        kargs[2] = kargs[2] * 4.0  # v: the least-squares weights
        return (tuple(kargs), *rest)

    monkeypatch.setattr(pose_bnb, "_setup", inflated)
    bad = []
    for family in ("uniform", "uneven", "beta"):
        bad += _violations(family, range(3))[0]
    assert any("> exact minimum" in b for b in bad)


def _dense_instance(seed: int, n: int = 40, inliers: int = 16, rival: int = 16
                    ) -> WeightedTLSProblem:
    """Inliers of one pose, as large a group consistent with another pose (its own
    clique in the consistency graph), and random outliers."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(-1, 1, (n, 3))
    b = np.empty_like(a)
    for sl in (slice(0, inliers), slice(inliers, inliers + rival)):
        R = Rotation.random(random_state=rng).as_matrix()
        b[sl] = a[sl] @ R.T + rng.normal(size=3) + 0.01 * rng.normal(size=(sl.stop - sl.start, 3))
    b[inliers + rival:] = rng.uniform(-1.5, 1.5, (n - inliers - rival, 3))
    return WeightedTLSProblem(a, b, noise_bound=0.0554)


@pytest.mark.parametrize("seed", range(3))
def test_certify_result_certifies_by_pose_search_when_the_listing_gives_up(
        monkeypatch: pytest.MonkeyPatch, seed: int) -> None:
    """With the clique listing made to give up (no maximal clique allowed), the pose search
    certifies the solver's pose of a 40-term problem, and the certificate records it; without
    ``pose_search`` the clique-number bound leaves the pose uncertified."""
    monkeypatch.setattr(certify_front, "MAX_CLIQUES", 0)
    p = _dense_instance(seed)
    res = solve_registration(p)
    plain = certify_result(p, res, time_limit=30.0)
    assert plain.certificate.method != "pose_bnb" and not plain.certificate.certified
    out = certify_result(p, res, time_limit=30.0, pose_search=True)
    cert = out.certificate
    assert cert.method == "pose_bnb" and cert.certified, cert.message
    assert cert.lower_bound <= out.cost <= res.cost * (1 + 1e-12)
    assert cert.upper_bound == pytest.approx(p.cost(out.rotation, out.translation), rel=1e-12)
    assert "pose_bnb: " in cert.backend_status and "proved" in cert.backend_status


def test_pose_search_certificates_pass_the_audit(monkeypatch: pytest.MonkeyPatch) -> None:
    """The audit's checks (upper bound is the pose's cost, lower bound below the exact
    minimum, certified only within the tolerance) on the certificate route, with every
    listing made to give up."""
    monkeypatch.setattr(certify_front, "MAX_CLIQUES", 0)
    bad = []
    for family in FAMILIES:
        for seed in range(2):
            rng = np.random.default_rng(9000 + 100 * FAMILIES.index(family) + seed)
            p = make_family(rng, family, int(rng.integers(6, 13)))
            res = solve_registration(p)
            out = certify_result(p, res, time_limit=30.0, pose_search=True)
            bad += [f"{family} {seed}: {v}" for v in
                    audit(p, out.certificate, out.rotation, out.translation)]
            exact = exact_optimum(p)
            if out.cost > exact + 1e-9 * (abs(exact) + out.certificate.weight_scale):
                bad.append(f"{family} {seed}: returned cost {out.cost} > exact {exact}")
            elif not out.certificate.certified:
                bad.append(f"{family} {seed}: exact optimum not certified "
                           f"({out.certificate.message})")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("seed", range(4))
def test_pose_search_finds_the_optimum_from_a_rival_pose(seed: int) -> None:
    """Started from the least-squares pose of a rival group (2 terms fewer than the inliers),
    the search must find a pose at least as good as the inliers' own refined pose and prove
    it within the tolerance: a wrongly pruned cell would lose it."""
    from solvers.certify.front import refine_pose
    from solvers.procrustes import weighted_procrustes

    p, _ = _normalised(_dense_instance(100 + seed, inliers=16, rival=14))
    Rr, tr = weighted_procrustes(p.source[16:30], p.target[16:30], np.ones(14))
    Ri, ti = refine_pose(p, *weighted_procrustes(p.source[:16], p.target[:16], np.ones(16)))
    assert p.cost(Ri, ti) < p.cost(Rr, tr) - 1.0
    pb = pose_bnb.pose_lower_bound(p, Rr, tr, tol=1e-3, time_limit=60.0)
    assert pb.complete and pb.rotation is not None
    assert pb.upper <= p.cost(Ri, ti) + 1e-9
    assert pb.lower <= pb.upper


def _sensitivity_instances() -> list[WeightedTLSProblem]:
    out = []
    for family in FAMILIES:
        rng = np.random.default_rng(11000 + FAMILIES.index(family))
        out.append(make_family(rng, family, 12))
    out += [_dense_instance(200 + s, inliers=12, rival=10) for s in range(3)]
    return out


@pytest.mark.parametrize("excess", [0.02, 0.3])
def test_no_proof_above_a_feasible_cost(excess: float) -> None:
    """Asked to prove that no pose costs less than a known pose's cost plus ``excess`` (times
    ``1 + its inlier cost``), the search must fail: that pose itself is a counterexample.
    A bound inflated anywhere near that pose (a shrunken uncertainty radius, a conflict
    test too strict) prunes its cell and "proves" it."""
    from solvers.certify.front import refine_pose

    proved = []
    for i, p0 in enumerate(_sensitivity_instances()):
        p, _ = _normalised(p0)
        res = solve_registration(p)
        R, t = refine_pose(p, res.rotation, res.translation)
        st = pose_bnb._stage(p, R, t, -excess, 60.0)
        if st.complete:
            proved.append(f"instance {i}: no pose below {st.lower!r} 'proved', but "
                          f"{p.cost(R, t)!r} is a pose's cost")
    assert not proved, "\n".join(proved)


@pytest.mark.parametrize("half_side", [0.0, 0.01, 0.05])
def test_recolouring_classes_hold_no_pair_a_cell_rotation_aligns(half_side: float) -> None:
    """Dense sampling: two terms of one class of the cell's colouring are never both within
    their noise bounds of any pose in the cell (rotations sampled from the rotation-vector cube,
    translation free: the pair's difference vectors must align within the sum of bounds)."""
    from solvers.certify._pose_kernels import _recolour
    from solvers.registration.pruning import consistency_edge_list

    rng = np.random.default_rng(5)
    n = 40
    a = rng.uniform(-2, 2, (n, 3))
    r0 = Rotation.random(random_state=rng).as_rotvec()
    b = a @ Rotation.from_rotvec(r0).as_matrix().T + 0.3 * rng.normal(size=(n, 3))
    tol = np.full(n, 1.0)
    edges = consistency_edge_list(a, b, tol, 1.0, rounding_slack=True)
    bits = pose_bnb._bitsets(n, edges)
    theta = min(np.sqrt(3) * half_side, np.pi)
    srot = 2 * np.sin(theta / 2)
    dvec = np.ascontiguousarray(a @ Rotation.from_rotvec(r0).as_matrix().T - b)
    cls = np.full(n, -1, dtype=np.int64)
    _recolour(np.arange(n, dtype=np.int64), np.zeros(n), np.ones(n), bits,
              np.zeros((n, n), dtype=np.int64), np.zeros(n, dtype=np.int64), dvec, a, tol,
              float(srot), np.zeros(n), cls)
    assert (cls >= 0).all()
    samples = r0 + half_side * rng.uniform(-1, 1, (2000, 3))
    samples = np.r_[samples, r0 + half_side * np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T]
    Rs = Rotation.from_rotvec(samples).as_matrix()
    aligned = 0
    for i in range(n):
        for j in range(i + 1, n):
            da, db = a[j] - a[i], b[j] - b[i]
            ok = np.linalg.norm(Rs @ da - db, axis=1) <= tol[i] + tol[j]
            aligned += int(ok.any())
            assert not (cls[i] == cls[j] and ok.any()), (i, j)
    assert aligned > n  # the test has pairs to separate


@pytest.mark.slow
@pytest.mark.parametrize("noise_bound", [0.05, 0.1])
def test_pose_bound_on_the_3dmatch_pair_is_below_every_known_pose(noise_bound: float) -> None:
    """On the real pair (940 FPFH correspondences) the gap-0.5 stage completes and its bound
    lies below the cost of every pose at hand: GNC's, the ground truth refined, and the best
    of many local refinements around GNC's (the last one is below GNC's at 0.05 m)."""
    from certpose.data.threedmatch import threedmatch_correspondences
    from solvers.certify.front import refine_pose
    from tests.conftest import require_data

    corr = threedmatch_correspondences(require_data("3dmatch", "gt.npy").parent)
    p = WeightedTLSProblem(corr.source, corr.target, noise_bound=noise_bound)
    res = solve_registration(p)
    pb = pose_bnb.pose_lower_bound(p, res.rotation, res.translation, tol=0.5, time_limit=600.0)
    assert pb.complete and pb.stages[-1][0] == 0.5
    G = corr.T_target_source
    costs = [res.cost, p.cost(*refine_pose(p, G[:3, :3], G[:3, 3]))]
    rng = np.random.default_rng(0)
    r0 = Rotation.from_matrix(res.rotation).as_rotvec()
    for _ in range(300):
        R = Rotation.from_rotvec(r0 + 0.05 * rng.normal(size=3)).as_matrix()
        costs.append(p.cost(*refine_pose(p, R, res.translation + 2 * noise_bound
                                         * rng.normal(size=3))))
    assert pb.lower <= min(costs)
    assert pb.lower >= stage_floor(pb.upper, p, res)


def stage_floor(upper: float, p: WeightedTLSProblem, res) -> float:  # noqa: ANN001
    """What a completed gap-0.5 stage proves for the candidate (less a rounding allowance)."""
    c_out = _outlier_cost(p, res.rotation, res.translation)
    return pose_bnb.stage_threshold(upper, c_out, 0.5) - 1e-6 * (1 + abs(upper))


@pytest.mark.parametrize("m", [1, 2, 7, 60])
def test_root_colouring_is_proper(m: int) -> None:
    """No edge joins two terms of one colour (a class must hold at most one inlier of any
    pose), including graphs with isolated vertices."""
    rng = np.random.default_rng(m)
    edges = np.array([(i, j) for i in range(m) for j in range(i + 1, m) if rng.random() < 0.4],
                     dtype=np.int64).reshape(-1, 2)
    col = pose_bnb._colouring(m, edges)
    assert col.shape == (m,) and (col >= 0).all()
    assert (col[edges[:, 0]] != col[edges[:, 1]]).all()
    complete = np.array([(i, j) for i in range(m) for j in range(i + 1, m)],
                        dtype=np.int64).reshape(-1, 2)
    assert np.unique(pose_bnb._colouring(m, complete)).size == m


def _interrupted(family: str, seeds: range, limits: tuple[int | None, ...] = (100, 1000, 3000, 10000, None)
                 ) -> list[str]:
    """The frontier search stopped after a few cells (two workers), then run to the end
    (``None``): its anytime bound must be below the enumerated minimum, and rise with the cells
    searched."""
    bad = []
    for seed in seeds:
        rng = np.random.default_rng(13000 + 100 * FAMILIES.index(family) + seed)
        p, _ = _normalised(make_family(rng, family, int(rng.integers(6, 13))))
        res = solve_registration(p)
        exact = exact_optimum(p)
        R = _rotate(res.rotation, 20.0, rng)
        search = pose_bnb.frontier(p, R, res.translation, workers=2)
        last = -np.inf
        for limit in limits:
            for gap in (0.3, 0.01, 1e-3):
                search.run(gap, time.perf_counter() + 60.0, max_cells=limit)
            where = f"{family} seed {seed} after {search.cells} cells"
            if search.lower > exact + 1e-9 * (1 + abs(exact)):
                bad.append(f"{where}: bound {search.lower!r} > exact minimum {exact!r}")
            if search.lower < last - 1e-12 * (1 + abs(last)):
                bad.append(f"{where}: bound fell from {last!r} to {search.lower!r}")
            last = search.lower
    return bad


@pytest.mark.parametrize("family", FAMILIES)
def test_an_interrupted_frontier_search_bounds_the_enumerated_optimum(
        monkeypatch: pytest.MonkeyPatch, family: str) -> None:
    """13 families x 2 instances, the search stopped after 100, 1000, 3000 and 10000 cells from
    a candidate 20 degrees off, then to the end (cells solved exactly only from 5 undecided
    terms down, so that it must split): every bound it reports is below the exact minimum and
    never falls (a cell left behind unrecorded, or recorded above its bound, would break
    one)."""
    monkeypatch.setattr(pose_bnb, "LEAF_TERMS", 5)
    bad = _interrupted(family, range(2))
    assert not bad, "\n".join(bad)


def test_an_interrupted_frontier_search_catches_an_inflated_bound(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Mutation check of the test above: bounds inflated 4x are reported above the exact
    minimum."""
    real = pose_bnb._setup

    def inflated(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        out = real(*args, **kwargs)
        if out is None or isinstance(out, str):
            return out
        kargs, *rest = out
        kargs = list(kargs)
        kargs[2] = kargs[2] * 4.0
        return (tuple(kargs), *rest)

    monkeypatch.setattr(pose_bnb, "_setup", inflated)
    monkeypatch.setattr(pose_bnb, "LEAF_TERMS", 5)
    bad = []
    for family in ("uniform", "uneven", "beta"):
        bad += _interrupted(family, range(2))
    assert any("> exact minimum" in b for b in bad)


@pytest.mark.parametrize("excess", [0.02, 0.3])
def test_frontier_search_proves_nothing_above_a_feasible_cost(excess: float) -> None:
    """As :func:`test_no_proof_above_a_feasible_cost`, for the frontier search: asked to
    raise its bound above a known pose's cost (cells kept up to far above it), it never
    gets there, and its bound stays below that cost."""
    from solvers.certify.front import refine_pose

    bad = []
    for i, p0 in enumerate(_sensitivity_instances()):
        p, _ = _normalised(p0)
        res = solve_registration(p)
        R, t = refine_pose(p, res.rotation, res.translation)
        u = p.cost(R, t)
        search = pose_bnb.frontier(p, R, t, cap=u + 10.0 * (1 + abs(u)), workers=2)
        done = search.run(-excess, time.perf_counter() + 60.0)
        if done or search.lower > u + 1e-9 * (1 + abs(u)):
            bad.append(f"instance {i}: bound {search.lower!r} (done: {done}) above the "
                       f"cost {u!r} of a pose")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("seed", range(3))
def test_frontier_stage_is_at_least_the_depth_first_one(seed: int) -> None:
    """At a completed stage the frontier search's bound is at least what the depth-first
    search from scratch proves at the same gap (its threshold, less the allowance)."""
    p, _ = _normalised(_dense_instance(300 + seed, inliers=12, rival=10))
    res = solve_registration(p)
    search = pose_bnb.frontier(p, res.rotation, res.translation)
    for gap in (0.3, 0.1, 0.02):
        st = pose_bnb._stage(p, res.rotation, res.translation, gap, 60.0)
        assert st.complete and st.found is None
        assert search.run(gap, time.perf_counter() + 60.0) and search.found is None
        assert search.lower >= st.lower - 1e-12 * (1 + abs(st.lower))
        assert search.lower <= search.u


def test_frontier_search_with_its_pool_compacted_at_every_pass(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The term pool compacted after every pass (cells' lists moved): the interrupted and
    finished searches still bound the enumerated optimum, and complete at the tolerance with
    the exact optimum within it."""
    from solvers.certify import pose_frontier

    monkeypatch.setattr(pose_frontier, "COMPACT_ROWS", 0)
    monkeypatch.setattr(pose_bnb, "LEAF_TERMS", 5)
    bad = []
    for family in ("uniform", "uneven", "beta", "grouped"):
        bad += _interrupted(family, range(2))
    assert not bad, "\n".join(bad)
    calls = []
    real = pose_frontier._Pool.compact

    def counting(self, rec):  # noqa: ANN001, ANN202
        calls.append(rec.shape[0])
        return real(self, rec)

    monkeypatch.setattr(pose_frontier._Pool, "compact", counting)
    bad, complete, runs = _violations("uniform", range(2))
    assert not bad, "\n".join(bad)
    assert complete == runs and calls
