"""File readers of certpose.io.points: every format on real files, and clear errors on bad files."""

from __future__ import annotations

import numpy as np
import pytest

from certpose.io.points import (
    load_bunny,
    read_correspondences,
    read_points,
    read_weights,
    scale_to_unit_cube,
    synthetic_shape,
)
from tests.conftest import require_data


@pytest.fixture
def points() -> np.ndarray:
    return np.random.default_rng(3).normal(size=(25, 3))


def _write_ply(path, pts: np.ndarray) -> None:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    assert o3d.io.write_point_cloud(str(path), cloud, write_ascii=False)


@pytest.mark.parametrize(
    "suffix", [".npy", ".csv", ".csv-header", ".txt", ".xyz", ".ply", ".pcd"]
)
def test_read_points_round_trip(tmp_path, points, suffix):
    if suffix == ".npy":
        path = tmp_path / "p.npy"
        np.save(path, points)
    elif suffix == ".csv":
        path = tmp_path / "p.csv"
        np.savetxt(path, points, delimiter=",", fmt="%.17g")
    elif suffix == ".csv-header":
        path = tmp_path / "p.csv"
        np.savetxt(path, points, delimiter=",", header="x,y,z", comments="", fmt="%.17g")
    elif suffix in (".txt", ".xyz"):
        path = tmp_path / f"p{suffix}"
        np.savetxt(path, points, fmt="%.17g")  # whitespace-separated
    else:
        path = tmp_path / f"p{suffix}"
        _write_ply(path, points)
    got = read_points(path)
    assert got.shape == points.shape and got.dtype == np.float64
    # Open3D's PLY keeps float64 positions; its PCD writer stores float32.
    atol = 1e-6 if suffix == ".pcd" else 1e-12
    np.testing.assert_allclose(got, points, rtol=0, atol=atol)


def test_read_points_real_files():
    bunny = read_points(require_data("bunny", "bun_zipper_res3.ply"))
    assert bunny.shape == (1889, 3)
    mug = read_points(require_data("ycbv", "models", "025_mug", "points.xyz"))
    assert mug.shape == (2621, 3)
    scan = read_points(require_data("3dmatch", "src.npy"))
    assert scan.shape == (15953, 3)


def test_load_bunny_in_unit_cube():
    raw = read_points(require_data("bunny", "bun_zipper_res3.ply"))
    bunny = load_bunny(require_data("bunny", "bun_zipper_res3.ply"))
    assert bunny.shape == raw.shape
    extent = bunny.max(axis=0) - bunny.min(axis=0)
    assert extent.max() == pytest.approx(1.0)
    np.testing.assert_allclose(bunny.max(axis=0), -bunny.min(axis=0), atol=1e-12)
    # A similarity of the raw vertices (shape preserved): distance ratios agree.
    d_raw = np.linalg.norm(raw[1:] - raw[:-1], axis=1)
    d_new = np.linalg.norm(bunny[1:] - bunny[:-1], axis=1)
    np.testing.assert_allclose(d_new / d_raw, 1.0 / (raw.max(0) - raw.min(0)).max(), rtol=1e-9)


def test_synthetic_shape_deterministic_and_asymmetric():
    a, b = synthetic_shape(), synthetic_shape()
    np.testing.assert_array_equal(a, b)
    assert a.shape == (2000, 3)
    assert np.all(np.abs(a) <= 0.5 + 1e-12)
    # Neither a mirror about a principal plane nor a half-turn about a principal axis maps
    # the shape onto itself: some flipped point lands far from every original point.
    from scipy.spatial import cKDTree

    centred = a - a.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov(centred.T))
    local = centred @ vecs
    tree = cKDTree(local)
    spacing = np.median(tree.query(local, k=2)[0][:, 1])
    for signs in ([-1, 1, 1], [1, -1, 1], [1, 1, -1], [-1, -1, 1], [-1, 1, -1], [1, -1, -1]):
        assert tree.query(local * signs)[0].max() > 4 * spacing, signs
    with pytest.raises(ValueError, match="n_points"):
        synthetic_shape(5)


def test_scale_to_unit_cube_rejects_degenerate():
    with pytest.raises(ValueError, match="coincident"):
        scale_to_unit_cube(np.ones((4, 3)))
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        scale_to_unit_cube(np.ones((4, 2)))


def test_read_correspondences_and_mismatch(tmp_path, points):
    np.save(tmp_path / "a.npy", points)
    np.save(tmp_path / "b.npy", points + 1.0)
    np.save(tmp_path / "c.npy", points[:-3])
    src, dst = read_correspondences(tmp_path / "a.npy", tmp_path / "b.npy")
    np.testing.assert_array_equal(src, points)
    np.testing.assert_array_equal(dst, points + 1.0)
    with pytest.raises(ValueError, match="25 points but target file .*c.npy.* has 22"):
        read_correspondences(tmp_path / "a.npy", tmp_path / "c.npy")


# Bad files: (file name, content writer, exception, message pattern).
def _bad_files(tmp_path):
    nan = np.ones((5, 3))
    nan[2, 1] = np.nan
    cases = {
        "missing.csv": (None, OSError, "does not exist"),
        "empty.csv": ("", ValueError, "empty"),
        "garbage.csv": ("hello world\nthis is not, a table\n", ValueError, "cannot parse"),
        "two_cols.csv": ("1,2\n3,4\n5,6\n", ValueError, r"shape \(N, 3\), got \(3, 2\)"),
        "ragged.txt": ("1 2 3\n4 5\n", ValueError, "cannot parse"),
        "nan.csv": ("1,2,3\n4,nan,6\n", ValueError, "NaN or inf values in 1 row"),
        "garbage.npy": ("not a numpy file", ValueError, "not a valid .npy"),
        "nan.npy": (nan, ValueError, "NaN or inf values in 1 row"),
        "wrong.npy": (np.ones((3, 4)), ValueError, r"shape \(N, 3\), got \(3, 4\)"),
        "garbage.ply": ("ply\nformat nonsense\n", ValueError, "not a valid PLY file"),
        "points.obj": ("v 1 2 3\n", ValueError, "unsupported suffix"),
        "binary.csv": (b"\xff\xfe\x00\x81", ValueError, "not a text file"),
    }
    out = []
    for name, (content, exc, pattern) in cases.items():
        path = tmp_path / name
        if isinstance(content, np.ndarray):
            np.save(path, content)
        elif isinstance(content, bytes):
            path.write_bytes(content)
        elif content is not None:
            path.write_text(content)
        out.append((path, exc, pattern))
    return out


def test_read_points_bad_files(tmp_path):
    for path, exc, pattern in _bad_files(tmp_path):
        with pytest.raises(exc, match=pattern) as info:
            read_points(path, name="source")
        msg = str(info.value)
        assert path.name in msg, msg
        assert "\n" not in msg, msg


def test_read_points_refuses_truncated_pcd_files(tmp_path, points):
    # Open3D reads a cut ASCII body as uninitialised rows and a header without POINTS as a
    # huge allocation (std::bad_alloc): both are refused with the file named, as for PLY.
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    for name, ascii_, compressed in (("a", True, False), ("b", False, False), ("c", False, True)):
        whole = tmp_path / f"{name}.pcd"
        assert o3d.io.write_point_cloud(str(whole), cloud, write_ascii=ascii_,
                                        compressed=compressed)
        np.testing.assert_allclose(read_points(whole), points, rtol=0, atol=1e-6)
        raw = whole.read_bytes()
        cut = tmp_path / f"{name}_cut.pcd"
        cut.write_bytes(raw[: len(raw) - 40])
        with pytest.raises(ValueError, match="not a valid PCD file: truncated") as info:
            read_points(cut, name="source")
        assert "source file" in str(info.value) and cut.name in str(info.value)
    # An ASCII body cut inside its last row (every row present, the last one short).
    text = (tmp_path / "a.pcd").read_text()
    (tmp_path / "short_row.pcd").write_text(text.rstrip("\n").rsplit(" ", 1)[0] + "\n")
    with pytest.raises(ValueError, match="row 25 of the body holds 2 values, not 3"):
        read_points(tmp_path / "short_row.pcd")
    (tmp_path / "header.pcd").write_text("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\n")
    with pytest.raises(ValueError, match="no DATA line"):
        read_points(tmp_path / "header.pcd")
    (tmp_path / "nopoints.pcd").write_text("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n"
                                           "COUNT 1 1 1\nDATA ascii\n1 2 3\n")
    with pytest.raises(ValueError, match="no POINTS line"):
        read_points(tmp_path / "nopoints.pcd")


def test_read_points_directory(tmp_path):
    with pytest.raises(OSError, match="not a regular file"):
        read_points(tmp_path)


def test_read_weights(tmp_path):
    w = np.linspace(0.0, 2.0, 7)
    np.save(tmp_path / "w.npy", w)
    np.savetxt(tmp_path / "w.csv", w, header="weight", comments="")
    np.save(tmp_path / "col.npy", w[:, None])
    for name in ("w.npy", "w.csv", "col.npy"):
        np.testing.assert_allclose(read_weights(tmp_path / name, n=7), w)
    with pytest.raises(ValueError, match=r"shape \(5,\), got \(7,\)"):
        read_weights(tmp_path / "w.npy", n=5)
    np.save(tmp_path / "neg.npy", -w)
    with pytest.raises(ValueError, match="negative"):
        read_weights(tmp_path / "neg.npy")
    np.save(tmp_path / "nan.npy", np.array([1.0, np.nan]))
    with pytest.raises(ValueError, match="NaN"):
        read_weights(tmp_path / "nan.npy")
    np.save(tmp_path / "mat.npy", np.ones((3, 3)))
    with pytest.raises(ValueError, match=r"shape \(N,\), got \(3, 3\)"):
        read_weights(tmp_path / "mat.npy")
    with pytest.raises(OSError, match="does not exist"):
        read_weights(tmp_path / "none.npy")
