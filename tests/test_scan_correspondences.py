"""FPFH correspondences of two point-cloud files (TEASER++'s example's recipe) and 3DMatch
``gt.log`` files: real scans, real open3d, real files."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from certpose.data.threedmatch import (
    NOISE_BOUND,
    TEASER_VOXEL_SIZE,
    load_threedmatch_pair,
    read_threedmatch_log,
    scan_correspondences,
    threedmatch_correspondences,
    threedmatch_log_pose,
)
from certpose.io.points import read_points
from solvers.lie import make_transform, transform_points
from tests.conftest import require_data


@pytest.fixture(scope="module")
def pair_dir():
    return require_data("3dmatch", "gt.npy").parent


def _write_ply(path, points) -> None:  # noqa: ANN001
    v = np.zeros(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    for k, axis in enumerate("xyz"):
        v[axis] = points[:, k]
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))


def _write_log(path, entries) -> None:  # noqa: ANN001
    """A 3DMatch gt.log: per entry the line 'i j n' and the 4x4 matrix, tab-separated."""
    lines = []
    for (i, j), T in entries.items():
        lines.append(f"{i}\t {j}\t 60\t")
        lines += ["\t".join(f"{v: .8e}" for v in row) for row in T]
    path.write_text("\n".join(lines) + "\n")


def test_files_of_the_shared_pair_give_its_correspondences_and_inliers(pair_dir):
    """The shared pair's files, read and matched: the same matches as the in-memory route, and
    under the true pose (gt.npy) dozens of inliers among mostly outliers (real FPFH)."""
    gt = np.load(pair_dir / "gt.npy")
    corr = scan_correspondences(pair_dir / "src.npy", pair_dir / "ref.npy", T_target_source=gt)
    assert corr.voxel_size == TEASER_VOXEL_SIZE and 500 <= corr.n <= 2000
    same = threedmatch_correspondences(pair_dir, voxel_size=TEASER_VOXEL_SIZE)
    np.testing.assert_array_equal(corr.source, same.source)
    np.testing.assert_array_equal(corr.target, same.target)
    np.testing.assert_allclose(corr.T_target_source, same.T_target_source, atol=1e-12)
    inliers = corr.residuals() < 2 * NOISE_BOUND
    assert 30 <= inliers.sum() <= 0.5 * corr.n
    # The matched points are points of the downsampled scans: within a voxel of a scan point.
    pair = load_threedmatch_pair(pair_dir)
    from scipy.spatial import cKDTree

    d = cKDTree(pair.source).query(corr.source)[0]
    assert d.max() < np.sqrt(3) * TEASER_VOXEL_SIZE


def test_a_moved_copy_of_the_bunny_is_matched_under_its_pose(tmp_path):
    """The bunny and a rotated, shifted copy in PLY files: under the known pose most mutual
    FPFH matches land within a voxel of their partner; under a 30-degree error almost none."""
    bunny = read_points(require_data("bunny", "bun_zipper_res3.ply"))
    angle = np.deg2rad(40.0)
    R = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0],
                  [0.0, 0.0, 1.0]])
    T = make_transform(R, np.array([0.3, -0.2, 0.1]))
    _write_ply(tmp_path / "src.ply", bunny)
    _write_ply(tmp_path / "tgt.ply", transform_points(T, bunny))
    voxel = 0.004
    corr = scan_correspondences(tmp_path / "src.ply", tmp_path / "tgt.ply", voxel_size=voxel,
                                T_target_source=T)
    assert corr.n >= 100
    assert np.mean(corr.residuals() < 2 * voxel) > 0.5
    wrong = make_transform(R @ np.array([[1.0, 0, 0], [0, np.cos(0.52), -np.sin(0.52)],
                                         [0, np.sin(0.52), np.cos(0.52)]]), T[:3, 3])
    moved = np.linalg.norm(transform_points(wrong, corr.source) - corr.target, axis=1)
    assert np.mean(moved < 2 * voxel) < 0.1


def test_without_ground_truth_residuals_are_refused(pair_dir):
    corr = scan_correspondences(pair_dir / "src.npy", pair_dir / "ref.npy", voxel_size=0.1)
    assert corr.T_target_source is None and corr.n > 0
    with pytest.raises(ValueError, match="no ground truth"):
        corr.residuals()


def test_bad_inputs_are_refused_clearly(tmp_path, pair_dir):
    src = pair_dir / "src.npy"
    with pytest.raises(FileNotFoundError, match="nowhere.ply"):
        scan_correspondences(tmp_path / "nowhere.ply", src)
    _write_ply(tmp_path / "empty.ply", np.zeros((0, 3)))
    with pytest.raises(ValueError, match="holds no points"):
        scan_correspondences(src, tmp_path / "empty.ply")
    pts = np.load(src)[:500].copy()
    pts[7, 1] = np.nan
    np.save(tmp_path / "nan.npy", pts)
    with pytest.raises(ValueError, match="NaN"):
        scan_correspondences(tmp_path / "nan.npy", src)
    with pytest.raises(ValueError, match="`voxel_size` must be positive"):
        scan_correspondences(src, src, voxel_size=-0.05)
    with pytest.raises(ValueError, match="T_target_source"):
        scan_correspondences(src, src, T_target_source=2 * np.eye(4))
    with pytest.raises(ValueError, match=r"shape \(4, 4\)"):
        scan_correspondences(src, src, T_target_source=np.eye(3))


def test_gt_log_convention_on_the_shared_pair(tmp_path, pair_dir):
    """Entry (i, j) maps fragment j into fragment i's frame: for source = fragment 0 (src) and
    target = fragment 1 (ref), either spelling gives the pose that makes the matches inliers."""
    gt = load_threedmatch_pair(pair_dir).T_target_source
    corr = threedmatch_correspondences(pair_dir)
    for entries in ({(1, 0): gt}, {(0, 1): np.linalg.inv(gt)}):
        _write_log(tmp_path / "gt.log", entries)
        T = threedmatch_log_pose(tmp_path / "gt.log", 0, 1)
        np.testing.assert_allclose(T, gt, atol=1e-6)
        r = np.linalg.norm(transform_points(T, corr.source) - corr.target, axis=1)
        assert (r < 2 * NOISE_BOUND).sum() >= 30
        back = threedmatch_log_pose(tmp_path / "gt.log", 1, 0)
        np.testing.assert_allclose(back @ T, np.eye(4), atol=1e-6)
    with pytest.raises(KeyError, match="fragments 0 and 2"):
        threedmatch_log_pose(tmp_path / "gt.log", 0, 2)


def test_malformed_gt_logs_are_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_threedmatch_log(tmp_path / "none.log")
    bad = tmp_path / "bad.log"
    bad.write_text("0 1 60\n1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(ValueError, match="blocks of 5"):
        read_threedmatch_log(bad)
    bad.write_text("0 1 60\n1 0 0 0\n0 1 0 0\n0 0 1 x\n0 0 0 1\n")
    with pytest.raises(ValueError, match="malformed block at line 1"):
        read_threedmatch_log(bad)
    bad.write_text("0 1 60\n2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(ValueError, match="line 1"):
        read_threedmatch_log(bad)
    _write_log(bad, {(0, 1): np.eye(4), (2, 3): make_transform(np.eye(3), np.ones(3))})
    log = read_threedmatch_log(bad)
    assert sorted(log) == [(0, 1), (2, 3)] and np.allclose(log[(2, 3)][:3, 3], 1.0)
