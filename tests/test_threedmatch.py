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


def test_default_dir_is_the_shared_data(pair_dir):
    assert default_threedmatch_dir().resolve() == pair_dir.resolve()


def test_load_pair(pair_dir):
    pair = load_threedmatch_pair(pair_dir)
    assert pair.source.shape == (15953, 3) and pair.target.shape == (18977, 3)
    T = pair.T_target_source
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)


def test_correspondences_hold_inliers_and_are_deterministic(pair_dir):
    corr = threedmatch_correspondences(pair_dir)
    assert corr.source.shape == corr.target.shape and corr.source.shape[1] == 3
    assert 500 <= corr.n <= 2000  # "about a thousand", like TEASER++'s example
    inliers = corr.residuals() < 2 * NOISE_BOUND
    # Real FPFH matches: mostly outliers, but enough inliers to register.
    assert 30 <= inliers.sum() <= 0.5 * corr.n
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
