"""The shared-source lower bound of weighted TLS (solvers.certify.groups)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from solvers import WeightedTLSProblem, solve_registration
from solvers.certify import certify_pose
from solvers.certify.groups import (
    ENUMERATE_MAX,
    _group_minima,
    _pair_minimum,
    _subset_tables,
    shared_source_bound,
)


def _grouped_problem(rng: np.random.Generator, n_points: int, k: int, *, beta: float = 0.01,
                     exact: bool = False, spread: float = 3.0):
    """``n_points`` source points with ``k`` candidate targets each (eq. (2)'s shape) around the
    point's image under a random pose, ``spread`` noise bounds away on average; with ``exact``
    (``k <= 4``) one on the image, the heaviest, and the others ``spread`` noise bounds off along
    the axes."""
    src = rng.uniform(-0.3, 0.3, (n_points, 3))
    R = Rotation.random(random_state=rng).as_matrix()
    t = rng.normal(size=3)
    img = src @ R.T + t
    tgt = np.repeat(img, k, axis=0) + rng.normal(scale=spread * beta, size=(n_points * k, 3))
    w = rng.uniform(0.5, 2.0, n_points * k)
    if exact:  # the true candidate on the image, the heaviest; the others far apart on axes
        off = np.tile(np.eye(3)[: k - 1], (n_points, 1)) * spread * beta
        tgt = np.repeat(img, k, axis=0)
        tgt[np.arange(n_points * k) % k != 0] += off
        w[::k] = 2.5
    betas = beta * rng.uniform(0.7, 1.3, n_points * k)
    return WeightedTLSProblem(np.repeat(src, k, axis=0), tgt, noise_bound=betas, weights=w), R, t


def _tls(q, b, w, beta, cbar2):  # noqa: ANN001, ANN202
    return float(w @ np.minimum(((b - q) ** 2).sum(axis=1) / beta**2, cbar2))


@pytest.mark.parametrize("k", [2, 3, 5, 7])
def test_a_group_minimum_is_the_tls_minimum_over_a_free_image(k: int) -> None:
    """Each group's value is the minimum over its free image point of its TLS sum: nothing found
    below it by a local search from every target and from random points (sound), and a search
    reaches it (exact)."""
    rng = np.random.default_rng(k)
    for _ in range(5):
        b = rng.normal(scale=0.01, size=(k, 3))
        w = rng.uniform(0.2, 3.0, k)
        beta = rng.uniform(0.005, 0.015, k)
        cbar2 = float(rng.uniform(0.5, 2.0))
        value = _group_minima(b[None], (w / beta**2)[None], w[None], cbar2)[0]
        starts = np.vstack([b, rng.normal(scale=0.02, size=(40, 3))])
        found = min(minimize(_tls, q0, args=(b, w, beta, cbar2), method="Nelder-Mead",
                             options={"xatol": 1e-12, "fatol": 1e-12, "maxiter": 4000}).fun
                    for q0 in starts)
        assert found >= value - 1e-9 * (1 + value)
        assert found <= value + 1e-6 * (1 + value)


@pytest.mark.parametrize(("seed", "k"), [(0, 3), (1, 6), (2, 9), (3, 12)])
def test_the_pair_kernel_is_the_numpy_minimum_over_all_subset_pairs_bit_for_bit(seed: int,
                                                                                 k: int) -> None:
    """The compiled pair minimum prunes the subset pairs (the cheapest first, then those whose
    costs alone can still beat the least value): it returns the minimum of the numpy formula
    over every pair of subsets, the same float. Groups of up to 12 correspondences (4,095
    subsets), the empty subsets (weight 0) included, and distances of pairs kept near, beyond
    and at the targets' spread."""
    rng = np.random.default_rng(seed)
    beta, cbar2 = 0.01, float(rng.uniform(0.5, 2.0))
    for d in (0.0, 0.01, 0.05, 0.2):
        b = [rng.normal(scale=0.01, size=(k, 3)), rng.normal(scale=0.01, size=(k, 3)) + [0.05, 0, 0]]
        w = [rng.uniform(0.5, 2.0, k), rng.uniform(0.5, 2.0, k)]
        (ci, wi, ki), (cj, wj, kj) = [
            tuple(x[0] for x in _subset_tables(bg[None], (wg / beta**2)[None], wg[None], cbar2))
            for bg, wg in zip(b, w, strict=True)]
        Ai, Aj = wi[:, None], wj[None, :]
        mu = np.where((Ai > 0) & (Aj > 0), Ai * Aj / np.maximum(Ai + Aj, 1e-300), 0.0)
        D = np.linalg.norm(ci[:, None, :] - cj[None, :, :], axis=2)
        want = float((ki[:, None] + kj[None, :] + mu * (D - d) ** 2).min())
        assert _pair_minimum(ci, wi, ki, cj, wj, kj, d) == want


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_pair_minimum_is_the_minimum_with_the_images_d_apart(seed: int) -> None:
    """Two groups whose images must stay ``d`` apart (a rigid motion keeps the distance of two
    source points): the pair's value is their least summed TLS cost over all such placements
    (a local search over ``q_i`` and the direction of ``q_j - q_i`` from many starts finds
    nothing lower, and reaches it), and at least the two groups' own minima."""
    rng = np.random.default_rng(seed)
    k, beta, cbar2 = 4, 0.01, 1.0
    b = [rng.normal(scale=0.01, size=(k, 3)), rng.normal(scale=0.01, size=(k, 3)) + [0.05, 0, 0]]
    w = [rng.uniform(0.5, 2.0, k), rng.uniform(0.5, 2.0, k)]
    d = float(rng.uniform(0.02, 0.08))  # the source points' distance: not the targets'
    tables = [tuple(x[0] for x in _subset_tables(bg[None], (wg / beta**2)[None], wg[None], cbar2))
              for bg, wg in zip(b, w, strict=True)]
    value = _pair_minimum(*tables[0], *tables[1], d)

    def cost(x):  # noqa: ANN001, ANN202
        q0 = x[:3]
        u = np.array([np.sin(x[3]) * np.cos(x[4]), np.sin(x[3]) * np.sin(x[4]), np.cos(x[3])])
        q1 = q0 + d * u
        return _tls(q0, b[0], w[0], beta, cbar2) + _tls(q1, b[1], w[1], beta, cbar2)

    def towards(q, y):  # noqa: ANN001, ANN202 - the direction angles of y - q
        v = (y - q) / np.linalg.norm(y - q)
        return np.arccos(np.clip(v[2], -1, 1)), np.arctan2(v[1], v[0])

    heads = [*b[0], b[0].mean(axis=0), *rng.normal(scale=0.03, size=(3, 3))]
    tails = [*b[1], b[1].mean(axis=0)]
    starts = [np.r_[q, towards(q, y)] for q in heads for y in tails]
    found = min(minimize(cost, x0, method="Nelder-Mead",
                         options={"xatol": 1e-12, "fatol": 1e-12, "maxiter": 8000}).fun
                for x0 in starts)
    singles = sum(float(t[2].min()) for t in tables)
    assert singles - 1e-12 <= value
    assert found >= value - 1e-9 * (1 + value)
    assert found <= value + 1e-5 * (1 + value)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(2, 6), n=st.integers(3, 30),
       near_identity=st.booleans())
def test_the_bound_never_exceeds_the_cost_of_any_pose(seed: int, k: int, n: int, near_identity: bool) -> None:
    rng = np.random.default_rng(seed)
    p, R, t = _grouped_problem(rng, n, k)
    bound = shared_source_bound(p)
    assert bound.groups == n and bound.chunked == 0
    poses = [(R, t)] + [(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
                        for _ in range(5)]
    if near_identity:  # tiny turns about the true pose, where the cost comes closest
        poses += [(Rotation.from_rotvec(rng.normal(scale=1e-7, size=3)).as_matrix() @ R,
                   t + rng.normal(scale=1e-9, size=3)) for _ in range(5)]
    for Ri, ti in poses:
        assert bound.lower <= p.cost(Ri, ti)


def test_the_bound_is_attained_when_each_group_has_an_exact_candidate() -> None:
    """Every source point's true candidate exactly on its image, the others far off: the true
    pose's cost is the bound (each group's best), and the certificate says globally optimal."""
    rng = np.random.default_rng(0)
    p, R, t = _grouped_problem(rng, 25, 4, exact=True, spread=40.0)
    bound = shared_source_bound(p)
    u = p.cost(R, t)
    assert bound.lower <= u <= bound.lower + 1e-9 * (1 + u)
    res = solve_registration(p)
    cert = certify_pose(p, res.rotation, res.translation)
    assert cert.certified and cert.lower_bound <= cert.upper_bound


def test_large_groups_are_chunked_and_stay_sound() -> None:
    rng = np.random.default_rng(5)
    k = ENUMERATE_MAX + 2
    p, R, t = _grouped_problem(rng, 3, k, spread=0.5)
    bound = shared_source_bound(p)
    assert bound.groups == 3 and bound.chunked == 3
    exact = sum(_group_minima(p.target[None, g * k:(g + 1) * k],
                              (p.weights / p.noise_bound**2)[None, g * k:(g + 1) * k],
                              p.weights[None, g * k:(g + 1) * k], p.cbar2)[0] for g in range(3))
    assert 0 < bound.lower <= exact + 1e-9
    assert bound.lower <= p.cost(R, t)


def test_one_to_one_correspondences_give_zero() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    p = WeightedTLSProblem(src, src + 0.01, noise_bound=0.05)
    bound = shared_source_bound(p)
    assert bound.lower == 0.0 and bound.groups == 0


@pytest.mark.slow
def test_the_demos_eq2_problem_gets_a_bound_from_its_candidates(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """`certpose pose --demo`'s eq. (2) problem (k candidate voxels per model point, a graph with
    too many maximal cliques): the certificate now bounds it by its candidates, a gap well below
    the trivial bound's, and still says it is not certified."""
    from certpose.cli import main
    from certpose.io.problems import load_problem

    path = tmp_path / "eq2.npz"
    assert main(["pose", "--demo", "--save-problem", str(path)]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("certificate:"))
    found = re.search(r"gap ([\d.]+), its cost ([\d.]+) at most ([\d.]+) above the optimum", line)
    assert found, line  # the printed bound: how far from optimal the eq. (2) minimiser can be
    assert 0 < float(found.group(1)) < 0.6 and 0 < float(found.group(3)) < float(found.group(2))
    f = load_problem(path)
    p = WeightedTLSProblem(f.source, f.target, noise_bound=f.noise_bound, weights=f.weights)
    res = solve_registration(p)
    cert = certify_pose(p, res.rotation, res.translation)
    bound = shared_source_bound(p)
    alone = shared_source_bound(p, pairs=False)  # the groups alone: the pairs add to it
    assert bound.pairs > 10 and bound.lower > alone.lower > 0
    assert bound.groups > 20 and cert.method == "shared_source"
    # Computed on the normalised problem: the greedy matching may break a near-tie otherwise.
    assert alone.lower < cert.lower_bound <= cert.upper_bound
    assert cert.lower_bound == pytest.approx(bound.lower, rel=1e-2)
    assert not cert.certified and cert.status.value == "iteration_limit"
    assert 0 < cert.relative_gap < 0.6
    assert "each source point placed independently" in cert.message
