"""The TEASER++ peer of `certpose bench`, judged by what the released binding exposes (its
solution has no `valid` field: reading it made every trial an error)."""

from __future__ import annotations

import numpy as np
import pytest

from certpose.bench.runner import SOLVERS, teaser_verdict
from certpose.bench.suites import InstanceSpec, load_instance
from certpose.io.points import synthetic_shape
from solvers import WeightedTLSProblem


def _protocol(ratio: float, seed: int):
    """The bench's own instance (what the peers are given)."""
    spec = InstanceSpec("synthetic", f"s{seed}", seed, 0, "protocol", (100, ratio))
    return load_instance(spec, {"synthetic": synthetic_shape()}, 0.01)


@pytest.fixture(scope="module")
def inst():
    return _protocol(0.5, 3)


def _truth_inliers(inst):
    p = WeightedTLSProblem(inst.source, inst.target, noise_bound=inst.noise_bound)
    return np.flatnonzero(p.inliers(inst.rotation, inst.translation))


def test_a_right_solution_is_a_success_with_its_tls_cost(inst):
    keep = _truth_inliers(inst)
    ok, status, T = teaser_verdict(inst, inst.rotation, inst.translation, clique=list(keep),
                                   translation_inliers=list(keep))
    assert ok and status.startswith("solved")
    cost = WeightedTLSProblem(inst.source, inst.target, noise_bound=inst.noise_bound).cost(
        inst.rotation, inst.translation)
    assert f"TLS cost {cost:.6g}" in status
    np.testing.assert_allclose(T[:3, :3], inst.rotation)


@pytest.mark.parametrize("case", ["small_clique", "no_translation_inliers", "not_rigid", "nan",
                                  "invalid_flag"])
def test_what_fixes_no_pose_is_a_failure(inst, case):
    keep = list(_truth_inliers(inst))
    R, t = inst.rotation, inst.translation
    kw = dict(clique=keep, translation_inliers=keep)
    if case == "small_clique":
        kw["clique"] = keep[:2]
    elif case == "no_translation_inliers":
        kw["translation_inliers"] = []
    elif case == "not_rigid":
        R = 2 * R
    elif case == "nan":
        t = np.full(3, np.nan)
    else:
        kw["valid"] = False
    ok, status, T = teaser_verdict(inst, R, t, **kw)
    assert not ok and status.startswith("failed")
    assert np.isfinite(T).all()


def test_a_binding_without_the_lists_is_judged_by_the_pose(inst):
    ok, status, _ = teaser_verdict(inst, inst.rotation, inst.translation, clique=None,
                                   translation_inliers=None)
    assert ok and "max clique n/a" in status


@pytest.mark.parametrize("ratio", [0.5, 0.9])
def test_the_released_binding_succeeds_where_certpose_does(ratio):
    pytest.importorskip("teaserpp_python")
    for seed in range(5):
        inst = _protocol(ratio, seed)
        ours, theirs = SOLVERS["gnc"](inst), SOLVERS["teaser++"](inst)
        assert ours.success and theirs.success, theirs.status
