"""The joint convex cell bound of the pose branch and bound
(:mod:`solvers.certify._convex_cell`): each term's envelope is convex, nondecreasing and below
the term; the cell's bound is below the cost of every pose sampled in the cell (synthetic and
real 3DMatch correspondences, cells near the identity included) and below the enumerated
minimum of small problems; it is tighter than the per-term bound on deep cells near the
optimum, and the search prunes cells with it that its other bounds leave."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from solvers import solve_registration
from solvers.certify import pose_bnb
from solvers.certify._convex_cell import ENV_COLS, _envelope, _term, cell_bound
from solvers.certify.front import _normalised
from solvers.problem import WeightedTLSProblem
from tests.test_certify_audit import FAMILIES, exact_optimum, make_family

CORNERS = np.array(np.meshgrid(*[[-1.0, 1.0]] * 3)).reshape(3, -1).T


def _terms(p: WeightedTLSProblem) -> tuple[np.ndarray, ...]:
    """The kernel's per-term arrays of ``p``: points, weights ``v``, outlier costs, norms, a
    rounding slack (writable copies: the search's own arrays, so no second compilation)."""
    a = np.array(p.source, dtype=np.float64, order="C")
    b = np.array(p.target, dtype=np.float64, order="C")
    v = np.ascontiguousarray(p.weights / p.noise_bound**2)
    wout = np.ascontiguousarray(p.cbar2 * p.weights)
    anorm = np.linalg.norm(a, axis=1)
    slack = 1e-12 * (1 + anorm + np.linalg.norm(b, axis=1))
    return a, b, v, wout, anorm, slack


def _bound(p: WeightedTLSProblem, rc: np.ndarray, rs: float, tc: np.ndarray, ts: float) -> float:
    """The convex bound of ``p``'s cost over the rotation vectors within ``rs`` of ``rc`` and the
    translations within ``ts`` of ``tc``."""
    a, b, v, wout, anorm, slack = _terms(p)
    theta = min(np.sqrt(3.0) * rs * (1 + 1e-12) + 1e-13, np.pi)
    R = Rotation.from_rotvec(rc).as_matrix()
    return float(cell_bound(a, b, v, wout, anorm, slack, np.arange(p.n, dtype=np.int64), R,
                            theta, np.asarray(tc, dtype=np.float64), float(ts)))


def _least_sampled(p: WeightedTLSProblem, rc: np.ndarray, rs: float, tc: np.ndarray, ts: float,
                   rng: np.random.Generator, n: int = 400) -> float:
    """The least cost over ``n`` random poses of the cell and the pairs of its corners."""
    rv = np.r_[rc + rs * CORNERS, rc + rs * rng.uniform(-1, 1, (n, 3))]
    tv = np.r_[tc + ts * CORNERS, tc + ts * rng.uniform(-1, 1, (n, 3))]
    Rs = Rotation.from_rotvec(rv).as_matrix()
    return min(p.cost(Rs[k], tv[k]) for k in range(len(rv)))


@settings(max_examples=300, deadline=None)
@given(v=st.floats(1e-3, 1e3), w=st.floats(1e-3, 1e3), c=st.floats(0.0, 5.0),
       lo=st.floats(0.0, 50.0), width=st.floats(0.0, 50.0))
def test_envelope_is_convex_nondecreasing_and_below_the_term(v: float, w: float, c: float,
                                                             lo: float, width: float) -> None:
    hi = lo + width
    env = np.empty(ENV_COLS)
    d = np.linspace(lo, hi, 801)
    phi = np.minimum(v * np.maximum(d - c, 0.0) ** 2, w)
    if not _envelope(v, w, c, lo, hi, env):
        assert v * max(lo - c, 0.0) ** 2 >= w  # the term is an outlier on the whole range
        return
    val = np.array([_term(env, x)[0] for x in d])
    slope = np.array([_term(env, x)[1] for x in d])
    tol = 1e-9 * (1 + w)
    assert (val <= phi + tol).all()
    assert (np.diff(val) >= -tol).all()
    assert (np.diff(slope) >= -1e-9 * (1 + abs(slope).max())).all()  # convex
    # The slope is the derivative (the bound's gradient is made of them), away from the kinks.
    h = 1e-6 * (1 + hi)
    kinks = np.array([c, env[1], lo, hi])
    for x in d[::40]:
        if np.abs(x - kinks).min() > 2 * h:
            num = (_term(env, x + h)[0] - _term(env, x - h)[0]) / (2 * h)
            assert num == pytest.approx(_term(env, x)[1], rel=1e-5, abs=1e-6 * (1 + w) / h)


def _synthetic(rng: np.random.Generator, n: int = 60) -> tuple[WeightedTLSProblem, np.ndarray,
                                                                 np.ndarray]:
    """Half inliers of a random pose (noise at the bound), half uniform outliers."""
    a = rng.uniform(-2, 2, (n, 3))
    R = Rotation.random(random_state=rng)
    t = rng.normal(size=3)
    b = a @ R.as_matrix().T + t + 0.03 * rng.normal(size=(n, 3))
    b[n // 2:] = rng.uniform(-3, 3, (n - n // 2, 3))
    w = rng.uniform(0.5, 2.0, n)
    return WeightedTLSProblem(a, b, noise_bound=0.06, weights=w), R.as_rotvec(), t


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("rs", [0.3, 0.03, 3e-3, 3e-4, 1e-6])
def test_cell_bound_below_every_sampled_pose(seed: int, rs: float) -> None:
    """Cells of every size, some holding the true pose and some beside it: the bound is below
    the least cost of 408 poses sampled in the cell."""
    rng = np.random.default_rng(seed)
    p, r0, t0 = _synthetic(rng)
    for _ in range(5):
        rc = r0 + rs * rng.uniform(-2, 2, 3)
        ts = 30 * rs
        tc = t0 + ts * rng.uniform(-2, 2, 3)
        lb = _bound(p, rc, rs, tc, ts)
        least = _least_sampled(p, rc, rs, tc, ts, rng)
        assert lb <= least + 1e-9 * (1 + abs(least)), (rc, tc, lb, least)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), log_rs=st.floats(-9, -1), scale=st.floats(0, 3),
       at_zero=st.booleans())
def test_cell_bound_near_the_identity(seed: int, log_rs: float, scale: float,
                                      at_zero: bool) -> None:
    """Cells about the identity rotation (the rotation vector's centre at or near 0, where
    ``exp`` is least well conditioned), of half-sides from 1e-9 to 0.1."""
    rng = np.random.default_rng(seed)
    n = 30
    a = rng.uniform(-2, 2, (n, 3))
    rs = 10.0**log_rs
    r_true = rs * rng.uniform(-1, 1, 3) * scale
    b = a @ Rotation.from_rotvec(r_true).as_matrix().T + 0.02 * rng.normal(size=(n, 3))
    b[n // 2:] += rng.normal(size=(n - n // 2, 3))
    p = WeightedTLSProblem(a, b, noise_bound=0.05)
    rc = np.zeros(3) if at_zero else rs * rng.uniform(-1, 1, 3)
    ts = 10 * rs
    tc = ts * rng.uniform(-1, 1, 3)
    lb = _bound(p, rc, rs, tc, ts)
    least = _least_sampled(p, rc, rs, tc, ts, rng, n=200)
    assert lb <= least + 1e-9 * (1 + abs(least))


@pytest.mark.parametrize("family", FAMILIES)
def test_cell_bound_below_the_enumerated_minimum(family: str) -> None:
    """Small problems of the audit's families (K = 5-12): every cell holding the optimal pose
    (offset at random inside cells of half-sides 0.1 rad and less) bounds below the exact
    minimum, and the smallest cells bound within 1e-3 of it (the bound is not vacuous)."""
    for seed in range(3):
        rng = np.random.default_rng(8000 + 100 * FAMILIES.index(family) + seed)
        p, _ = _normalised(make_family(rng, family, int(rng.integers(5, 13))))
        res = solve_registration(p)
        exact = exact_optimum(p)
        if p.cost(res.rotation, res.translation) > exact + 1e-9 * (1 + abs(exact)):
            continue  # the solver missed the optimum: no optimal pose to put in a cell
        r0 = Rotation.from_matrix(res.rotation).as_rotvec()
        # Cells of 0.1 to 1e-4 rad, the last moving every point by at most 1e-3 noise bounds.
        small = 1e-3 * p.noise_bound.min() / (1 + np.linalg.norm(p.source, axis=1).max())
        for rs in (0.1, 0.01, 1e-3, small):
            ts = rs * (1 + np.linalg.norm(p.source, axis=1).max())
            rc = r0 + rs * rng.uniform(-1, 1, 3)
            tc = res.translation + ts * rng.uniform(-1, 1, 3)
            lb = _bound(p, rc, rs, tc, ts)
            assert lb <= exact + 1e-9 * (1 + abs(exact)), (family, seed, rs, lb, exact)
        assert lb >= exact - 1e-3 * (1 + abs(exact)), (family, seed, lb, exact)


def _interval_bound(a, b, v, wout, R, tc, rs, ts) -> float:  # noqa: ANN001
    """The search's per-term bound of a cell: each term's least residual over the cell
    (nearest point of the translation box, less the rotations' reach ``2 sin(theta/2) |a|``)."""
    theta = min(np.sqrt(3.0) * rs, np.pi)
    e = a @ R.T + tc - b
    near = np.linalg.norm(np.maximum(np.abs(e) - ts, 0.0), axis=1)
    low = np.maximum(near - 2 * np.sin(theta / 2) * np.linalg.norm(a, axis=1), 0.0)
    return float(np.minimum(v * low**2, wout).sum())


@pytest.mark.slow
@pytest.mark.parametrize("noise_bound", [0.05, 0.1])
def test_cell_bound_on_the_3dmatch_pair(noise_bound: float) -> None:
    """The real pair's correspondences in the search's frame (about the candidate's inlier
    centroid, in units of the noise bound): cells near GNC's pose bound below every pose
    sampled in them, and the deep ones (rotation half-side 1e-3 and less) bound at least
    the per-term bound plus half the distance from it to the least sampled cost."""
    from certpose.data.threedmatch import threedmatch_correspondences
    from solvers.registration import unit_scale_problem
    from tests.conftest import require_data

    corr = threedmatch_correspondences(require_data("3dmatch", "gt.npy").parent)
    unit, _ = unit_scale_problem(corr.source, corr.target, noise_bound=noise_bound,
                                 weights=None, cbar2=1.0)
    pn, _ = _normalised(unit)
    res = solve_registration(pn)
    u = pn.cost(res.rotation, res.translation)
    args, *_ = pose_bnb._setup(pn, res.rotation, res.translation, u, u)
    a, b, v, wout = args[:4]
    # The core's terms in the search's frame (the candidate pose is (R, 0) there): cost
    # sum min(v |r|^2, wout).
    p = WeightedTLSProblem(a, b, noise_bound=np.sqrt(wout / v), weights=wout, cbar2=1.0)
    r0 = Rotation.from_matrix(res.rotation).as_rotvec()
    rng = np.random.default_rng(1)
    tighter = 0
    for rs in (0.01, 1e-3, 3e-4):
        for _ in range(4):
            rc = r0 + rs * rng.uniform(-1.5, 1.5, 3)
            ts = 10 * rs
            tc = ts * rng.uniform(-1.5, 1.5, 3)
            lb = _bound(p, rc, rs, tc, ts)
            least = _least_sampled(p, rc, rs, tc, ts, rng, n=300)
            assert lb <= least + 1e-9 * (1 + abs(least))
            if rs <= 1e-3:
                R = Rotation.from_rotvec(rc).as_matrix()
                cheap = _interval_bound(a, b, v, wout, R, tc, rs, ts)
                tighter += lb >= cheap + 0.5 * (least - cheap)
    assert tighter == 8


def test_search_prunes_cells_with_it_the_other_bounds_leave() -> None:
    """In the frontier search of a 60-term problem towards a gap of 1e-3, the convex bound
    prunes cells that the interval, least-squares and colouring bounds left below the
    threshold (depth profile, column 5), and the search completes."""
    rng = np.random.default_rng(3)
    p, _, _ = _synthetic(rng)
    p, _ = _normalised(p)
    res = solve_registration(p)
    pb = pose_bnb.pose_lower_bound(p, res.rotation, res.translation, tol=1e-3, time_limit=60.0)
    assert pb.complete
    prof = pb.depth_profile
    assert prof[:, 4].sum() > 0 and prof[:, 5].sum() > 0, prof[prof[:, 0] > 0]


@pytest.mark.parametrize("seed", range(3))
def test_relaxation_gradient_and_hessian_are_its_derivatives(seed: int) -> None:
    """The relaxation's gradient (the bound's linear term: a wrong one would make the bound
    unsound) and Hessian match central differences at random points of a cell."""
    from solvers.certify._convex_cell import _value, cell_terms

    rng = np.random.default_rng(seed)
    p, r0, t0 = _synthetic(rng)
    a, b, v, wout, anorm, slack = _terms(p)
    rs, ts = 0.02, 0.05
    R = Rotation.from_rotvec(r0 + rs * rng.uniform(-1, 1, 3)).as_matrix()
    tc = t0 + ts * rng.uniform(-1, 1, 3)
    E, Q, env = np.empty((p.n, 3)), np.empty((p.n, 3)), np.empty((p.n, ENV_COLS))
    n, _ = cell_terms(a, b, v, wout, anorm, slack, np.arange(p.n, dtype=np.int64), R, tc[0],
                      tc[1], tc[2], np.sqrt(3) * rs, ts, E, Q, env)
    assert n > 10
    grad, hess, scratch_g, scratch_h = np.empty(6), np.empty((6, 6)), np.empty(6), np.empty((6, 6))
    h = 1e-6
    for _ in range(5):
        z = np.r_[rs * rng.uniform(-1, 1, 3), ts * rng.uniform(-1, 1, 3)]
        _value(E, Q, env, n, z, grad, hess, 2)
        num_g, num_h = np.empty(6), np.empty((6, 6))
        for k in range(6):
            dz = np.zeros(6)
            dz[k] = h
            fp = _value(E, Q, env, n, z + dz, scratch_g, scratch_h, 1)
            gp = scratch_g.copy()
            fm = _value(E, Q, env, n, z - dz, scratch_g, scratch_h, 1)
            num_g[k] = (fp - fm) / (2 * h)
            num_h[:, k] = (gp - scratch_g) / (2 * h)
        scale = 1 + np.abs(grad).max()
        assert np.allclose(grad, num_g, rtol=1e-4, atol=1e-4 * scale), (grad, num_g)
        # Hessians agree except where a term crosses a kink within h (rare at random z).
        assert np.allclose(hess, num_h, rtol=1e-3, atol=1e-3 * (1 + np.abs(hess).max()))
