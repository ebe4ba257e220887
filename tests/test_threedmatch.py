"""The 3DMatch pair loader and its putative FPFH correspondences (real data, real open3d)."""

from __future__ import annotations

import numpy as np
import pytest

from certpose.data.threedmatch import (
    NOISE_BOUND,
    default_threedmatch_dir,
    fpfh_correspondences,
    load_threedmatch_pair,
    threedmatch_correspondences,
)
from tests.conftest import require_data


@pytest.fixture(scope="module")
def pair_dir():
    return require_data("3dmatch", "gt.npy").parent


@pytest.fixture(scope="module")
def corr(pair_dir):
    return threedmatch_correspondences(pair_dir)


def test_default_dir_is_the_shared_data(pair_dir):
    assert default_threedmatch_dir().resolve() == pair_dir.resolve()


def test_load_pair(pair_dir):
    pair = load_threedmatch_pair(pair_dir)
    assert pair.source.shape == (15953, 3) and pair.target.shape == (18977, 3)
    T = pair.T_target_source
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)


def test_correspondences_hold_inliers(corr):
    assert corr.source.shape == corr.target.shape and corr.source.shape[1] == 3
    assert 500 <= corr.n <= 2000  # "about a thousand", like TEASER++'s example
    inliers = corr.residuals() < 2 * NOISE_BOUND
    # Real FPFH matches: mostly outliers, but enough inliers to register.
    assert 30 <= inliers.sum() <= 0.5 * corr.n


def test_correspondences_are_deterministic(pair_dir, corr):
    again = threedmatch_correspondences(pair_dir)
    np.testing.assert_array_equal(corr.source, again.source)
    np.testing.assert_array_equal(corr.target, again.target)


def test_mutual_matches_of_a_scan_with_itself_are_exact(pair_dir):
    pts = load_threedmatch_pair(pair_dir).source[::4]
    src, tgt = fpfh_correspondences(pts, pts + [1.0, 2.0, 3.0], voxel_size=0.05)
    # A shifted copy of a scan: the same voxels (up to rounding at voxel borders), the same
    # features: nearly every match is the point's own copy.
    assert src.shape[0] > 100
    exact = np.linalg.norm(tgt - src - [1.0, 2.0, 3.0], axis=1) < 1e-6
    assert exact.mean() > 0.9


def test_missing_folder_and_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_threedmatch_pair(tmp_path / "nowhere")
    np.save(tmp_path / "src.npy", np.zeros((4, 3)))
    with pytest.raises(FileNotFoundError, match="lacks ref.npy, gt.npy"):
        load_threedmatch_pair(tmp_path)


def test_malformed_arrays(tmp_path):
    np.save(tmp_path / "src.npy", np.zeros((4, 2)))
    np.save(tmp_path / "ref.npy", np.zeros((4, 3)))
    np.save(tmp_path / "gt.npy", np.eye(4))
    with pytest.raises(ValueError, match="3"):
        load_threedmatch_pair(tmp_path)
    np.save(tmp_path / "src.npy", np.zeros((4, 3)))
    np.save(tmp_path / "gt.npy", 2 * np.eye(4))
    with pytest.raises(ValueError, match="gt.npy"):
        load_threedmatch_pair(tmp_path)
    with pytest.raises(ValueError, match="`voxel_size` must be positive"):
        fpfh_correspondences(np.zeros((4, 3)), np.zeros((4, 3)), voxel_size=0.0)


def test_default_solver_registers_the_pair(corr):
    from certpose.api import register
    from solvers.lie import rotation_error_deg

    res = register(corr.source, corr.target, noise_bound=NOISE_BOUND)
    T, G = res.T_target_source, corr.T_target_source
    assert res.success
    assert rotation_error_deg(T[:3, :3], G[:3, :3]) < 5
    assert np.linalg.norm(T[:3, 3] - G[:3, 3]) < 0.1
    # A dense graph with tied maximum cliques: the search proved the clique maximum.
    assert res.info["graph_edges"] > 50_000 and res.info["max_clique_exact"]
    assert res.info["tied_max_cliques"] > 1


def test_certify_on_the_dense_pair_bounds_by_the_clique_number(corr):
    """Too many maximal cliques to bound one by one: a sound bound, not a certificate and not
    a missing bound; the clique number's, or tighter, the branch and bound over poses' that
    ``register`` runs (``pose_search``)."""
    from certpose.api import register
    from solvers import solve_registration
    from solvers.certify import certify_result
    from solvers.registration.solve import unit_scale_problem

    # scope="full": the full problem's own bound (the default "auto" then certifies the
    # rotation subproblem, tests/test_certify_real_scans.py).
    res = register(corr.source, corr.target, noise_bound=NOISE_BOUND, certify=True, time_limit=5,
                   scope="full")
    cert = res.certificate
    assert not cert.certified and cert.status.value == "iteration_limit"
    assert cert.method in ("clique_number", "pose_bnb")
    assert np.isfinite(cert.lower_bound) and cert.lower_bound <= cert.upper_bound
    # No pose keeps more inliers than the largest consistent set: about N - omega.
    assert cert.lower_bound >= corr.n - 2 * res.info["max_clique_size"]
    # Without the pose search (certify_result's default): the clique number, as before.
    unit, _ = unit_scale_problem(corr.source, corr.target, noise_bound=NOISE_BOUND)
    plain = certify_result(unit, solve_registration(unit, method="auto"), time_limit=5)
    assert plain.certificate.method == "clique_number"
    assert "clique number" in plain.certificate.message


def test_certify_skip_futile_does_not_search_a_clique_number_that_cannot_certify(corr):
    """With ``skip_futile`` (the MLE's certifier), a clique-number bound whose best possible gap
    is above the tolerance is not searched: "not attempted", bounded by 0, the same pose and
    upper bound, and the bound it replaces did not certify either."""
    from solvers import solve_registration
    from solvers.certify import certify_result
    from solvers.certify.front import _clique_number_best_gap, _normalised
    from solvers.registration.solve import unit_scale_problem

    unit, _ = unit_scale_problem(corr.source, corr.target, noise_bound=NOISE_BOUND)
    res = solve_registration(unit, method="auto")
    plain = certify_result(unit, res, time_limit=5).certificate
    skip = certify_result(unit, res, time_limit=5, skip_futile=True).certificate
    assert plain.method == "clique_number" and not plain.certified
    best, k = _clique_number_best_gap(_normalised(unit)[0], res.rotation, res.translation)
    assert plain.tol < best <= plain.relative_gap
    assert not skip.certified and skip.status.value == "iteration_limit"
    assert "clique-number bound not attempted" in skip.message and f"of {k} " in skip.message
    assert skip.lower_bound == 0.0 and skip.upper_bound == plain.upper_bound
