"""RGB-D input: intrinsics, frames, back-projection, structured point clouds."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose.geometry.rgbd import (
    CameraIntrinsics,
    RGBDFrame,
    StructuredPointCloud,
    backproject,
    group_voxels,
    load_rgbd,
)
from solvers.lie import make_transform

K_SMALL = CameraIntrinsics(fx=2.0, fy=4.0, cx=1.0, cy=2.0, width=5, height=4)


def test_intrinsics_matrix_round_trip():
    K = np.array([[500.0, 0.0, 320.5], [0.0, 510.0, 239.5], [0.0, 0.0, 1.0]])
    cam = CameraIntrinsics.from_matrix(K, 640, 480)
    np.testing.assert_array_equal(cam.K, K)
    assert cam.shape == (480, 640)


@pytest.mark.parametrize(
    "K, match",
    [
        (np.eye(2), r"shape \(3, 3\), got \(2, 2\)"),
        (np.array([[1.0, 0.5, 1], [0, 1, 1], [0, 0, 1]]), "skew"),
        (np.array([[1.0, 0, 1], [0, 1, 1], [0, 1, 1]]), "not a pinhole"),
        (np.array([[np.nan, 0, 1], [0, 1, 1], [0, 0, 1]]), "NaN"),
    ],
)
def test_intrinsics_bad_matrix(K, match):
    with pytest.raises(ValueError, match=match):
        CameraIntrinsics.from_matrix(K, 4, 3)


def test_intrinsics_bad_values():
    with pytest.raises(ValueError, match="`fx` must be positive"):
        CameraIntrinsics(0.0, 1.0, 0.0, 0.0, 4, 3)
    with pytest.raises(ValueError, match="`width` must be a positive integer"):
        CameraIntrinsics(1.0, 1.0, 0.0, 0.0, 0, 3)


def test_backproject_hand_computed_pixels():
    depth = np.zeros((4, 5))
    depth[1, 3] = 2.0  # u=3, v=1: x = (3-1)*2/2 = 2, y = (1-2)*2/4 = -0.5
    depth[0, 0] = 1.0  # u=0, v=0: x = (0-1)/2 = -0.5, y = (0-2)/4 = -0.5
    depth[3, 1] = 4.0  # u=1, v=3: x = 0, y = (3-2)*4/4 = 1
    points, pixels = backproject(depth, K_SMALL)
    np.testing.assert_array_equal(pixels, [[0, 0], [1, 3], [3, 1]])
    np.testing.assert_allclose(points, [[-0.5, -0.5, 1.0], [2.0, -0.5, 2.0], [0.0, 1.0, 4.0]])
    assert pixels.dtype == np.int64


def test_backproject_mask_and_projection_round_trip():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 2.0, size=(4, 5))
    depth[2, 2] = 0.0
    mask = np.zeros((4, 5), bool)
    mask[1:3, 1:4] = True
    points, pixels = backproject(depth, K_SMALL, mask=mask)
    assert len(points) == 5  # 6 masked pixels, one has no depth
    assert mask[pixels[:, 0], pixels[:, 1]].all()
    u, v, z = K_SMALL.project(points)
    np.testing.assert_allclose(u, pixels[:, 1], atol=1e-12)
    np.testing.assert_allclose(v, pixels[:, 0], atol=1e-12)
    np.testing.assert_allclose(z, depth[pixels[:, 0], pixels[:, 1]])


def test_backproject_errors():
    with pytest.raises(ValueError, match=r"Expected `depth` to have shape \(4, 5\), got \(4, 6\)"):
        backproject(np.ones((4, 6)), K_SMALL)
    with pytest.raises(ValueError, match="no valid"):
        backproject(np.zeros((4, 5)), K_SMALL)
    mask = np.zeros((4, 5), bool)
    with pytest.raises(ValueError, match="`mask` is empty"):
        backproject(np.ones((4, 5)), K_SMALL, mask=mask)
    mask[0, 0] = True
    depth = np.ones((4, 5))
    depth[0, 0] = 0.0
    with pytest.raises(ValueError, match="inside `mask`"):
        backproject(depth, K_SMALL, mask=mask)
    bad = np.ones((4, 5))
    bad[1, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        backproject(bad, K_SMALL)


def _color(h=4, w=5):
    return np.full((h, w, 3), 128, dtype=np.uint8)


def test_frame_validation():
    depth = np.ones((4, 5))
    frame = RGBDFrame(_color(), depth, K_SMALL)
    np.testing.assert_array_equal(frame.T_world_camera, np.eye(4))
    assert frame.mask is None
    with pytest.raises(ValueError, match=r"Expected `color` to have shape \(4, 5, 3\)"):
        RGBDFrame(_color(4, 6), depth, K_SMALL)
    with pytest.raises(ValueError, match=r"Expected `depth` to have shape \(4, 5\)"):
        RGBDFrame(_color(), np.ones((4, 6)), K_SMALL)
    with pytest.raises(ValueError, match="zero everywhere"):
        RGBDFrame(_color(), np.zeros((4, 5)), K_SMALL)
    nan_depth = depth.copy()
    nan_depth[0, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        RGBDFrame(_color(), nan_depth, K_SMALL)
    with pytest.raises(ValueError, match="negative"):
        RGBDFrame(_color(), -depth, K_SMALL)
    with pytest.raises(ValueError, match="raw sensor units"):
        RGBDFrame(_color(), depth * 1500.0, K_SMALL)
    with pytest.raises(TypeError, match="uint8"):
        RGBDFrame(_color().astype(float), depth, K_SMALL)
    with pytest.raises(ValueError, match="`mask` is empty"):
        RGBDFrame(_color(), depth, K_SMALL, mask=np.zeros((4, 5), bool))
    with pytest.raises(ValueError, match=r"Expected `mask` to have shape \(4, 5\)"):
        RGBDFrame(_color(), depth, K_SMALL, mask=np.ones((5, 4), bool))
    with pytest.raises(ValueError, match="T_world_camera"):
        RGBDFrame(_color(), depth, K_SMALL, T_world_camera=np.ones((4, 4)))


def test_frame_backproject_world_and_colors():
    depth = np.zeros((4, 5))
    depth[1, 3] = 2.0
    color = _color()
    color[1, 3] = (255, 0, 51)
    T = make_transform(Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix(), [1.0, 2.0, 3.0])
    frame = RGBDFrame(color, depth, K_SMALL, T)
    p_world, px = frame.backproject(world=True)
    expected = T[:3, :3] @ np.array([2.0, -0.5, 2.0]) + T[:3, 3]
    np.testing.assert_allclose(p_world[0], expected)
    np.testing.assert_allclose(frame.colors_at(px), [[1.0, 0.0, 0.2]])



def test_frame_pixels_of_inverts_backproject_and_flags_the_rest():
    depth = np.zeros((4, 5))
    depth[1, 3] = 2.0
    T = make_transform(Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix(), [1.0, 2.0, 3.0])
    frame = RGBDFrame(_color(), depth, K_SMALL, T)
    p_world, px = frame.backproject(world=True)
    behind = T[:3, :3] @ np.array([0.0, 0.0, -1.0]) + T[:3, 3]
    outside = T[:3, :3] @ np.array([50.0, 0.0, 1.0]) + T[:3, 3]
    row, col, z, inside = frame.pixels_of(np.vstack([p_world, behind, outside]))
    assert (row[0], col[0]) == tuple(px[0]) and z[0] == pytest.approx(2.0)
    assert inside.tolist() == [True, False, False]
    assert (row[1], col[1]) == (-1, -1)
    with pytest.raises(ValueError, match="points"):
        frame.pixels_of(np.zeros((2, 2)))

def test_load_rgbd_reads_files_and_names_missing_ones(tmp_path):
    import imageio.v3 as iio

    raw = np.arange(20, dtype=np.uint16).reshape(4, 5) * 100
    iio.imwrite(tmp_path / "d.png", raw)
    iio.imwrite(tmp_path / "c.png", _color())
    frame = load_rgbd(tmp_path / "c.png", tmp_path / "d.png", K_SMALL, depth_scale=1000.0)
    np.testing.assert_allclose(frame.depth, raw / 1000.0)
    with pytest.raises(FileNotFoundError, match="missing.png"):
        load_rgbd(None, tmp_path / "missing.png", K_SMALL)


def test_read_image_gives_imageios_arrays(tmp_path):
    # PNGs read by Pillow directly (plain modes) or through imageio (the others) come out as
    # imageio.v3.imread gives them: same dtype, shape and values, writeable.
    import imageio.v3 as iio
    from PIL import Image

    from certpose.geometry.rgbd import read_image

    rng = np.random.default_rng(0)
    rgba = rng.integers(0, 256, size=(6, 7, 4), dtype=np.uint8)
    images = {
        "L": Image.fromarray(rgba[..., 0]),
        "LA": Image.fromarray(rgba[..., :2], mode="LA"),
        "RGB": Image.fromarray(rgba[..., :3]),
        "RGBA": Image.fromarray(rgba),
        "I;16": Image.fromarray(rng.integers(0, 65536, size=(6, 7), dtype=np.uint16)),
        "P": Image.fromarray(rgba[..., :3]).convert("P", palette=Image.Palette.ADAPTIVE, colors=5),
        "1": Image.fromarray(rgba[..., 0] > 127),
    }
    for mode, image in images.items():
        assert image.mode == mode
        path = tmp_path / f"{mode.replace(';', '_')}.png"
        image.save(path)
        got, ref = read_image(path), iio.imread(path)
        assert got.dtype == ref.dtype and got.shape == ref.shape, mode
        np.testing.assert_array_equal(got, ref, err_msg=mode)
        assert got.flags.writeable
    # The palette image comes out in colour (imageio's conversion), not as palette indices.
    assert read_image(tmp_path / "P.png").shape == (6, 7, 3)
    Image.fromarray(rgba[..., :3]).save(tmp_path / "c.bmp")  # not a PNG: imageio
    np.testing.assert_array_equal(read_image(tmp_path / "c.bmp"), rgba[..., :3])
    (tmp_path / "bad.png").write_bytes(b"not an image")
    with pytest.raises(OSError, match="Cannot read the depth image"), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # imageio's plugins, tried in turn
        read_image(tmp_path / "bad.png", "depth")
    with pytest.raises(FileNotFoundError, match="nothing.png"):
        read_image(tmp_path / "nothing.png")


def test_read_image_ycbv_frame_as_imageio():
    import imageio.v3 as iio

    from certpose.geometry.rgbd import read_image
    from tests.conftest import require_data

    folder = require_data("ycbv", "0000")
    for suffix in ("color.png", "depth.png", "label.png"):
        path = folder / f"000001-{suffix}"
        got, ref = read_image(path), iio.imread(path)
        assert got.dtype == ref.dtype and got.shape == ref.shape, suffix
        np.testing.assert_array_equal(got, ref, err_msg=suffix)


def test_structured_cloud_validation():
    pts = np.zeros((3, 3))
    with pytest.raises(ValueError, match=r"Expected `descriptors` to have shape \(3, d\)"):
        StructuredPointCloud(pts, np.zeros((2, 4)))
    bad = np.zeros((3, 4))
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        StructuredPointCloud(pts, bad)
    with pytest.raises(ValueError, match="at least 1"):
        StructuredPointCloud(np.zeros((0, 3)), np.zeros((0, 4)))
    with pytest.raises(ValueError, match=r"within \[0, 1\]"):
        StructuredPointCloud(pts, np.zeros((3, 2)), colors=np.full((3, 3), 2.0))


def test_group_voxels_matches_unique_rows():
    rng = np.random.default_rng(3)
    keys = rng.integers(-4, 4, size=(500, 3))
    rows, inverse, counts = group_voxels(keys)
    ref_rows, ref_inv, ref_counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    np.testing.assert_array_equal(rows, ref_rows)
    np.testing.assert_array_equal(inverse, ref_inv.reshape(-1))
    np.testing.assert_array_equal(counts, ref_counts)
    # Keys so spread that flat codes would overflow int64 take the row-wise path.
    far = np.array([[0, 0, 0], [2**40, -(2**40), 2**40], [0, 0, 0]])
    rows, inverse, counts = group_voxels(far)
    np.testing.assert_array_equal(rows[inverse], far)
    assert counts.tolist() == [2, 1] and group_voxels(np.zeros((0, 3), int))[0].shape == (0, 3)
    # Dense keys (counted per cell) and sparse ones (sorted): np.unique's results either way.
    for spread, n in ((3, 20_000), (1000, 50), (60, 3000)):
        keys = rng.integers(-spread, spread, size=(n, 3))
        rows, inverse, counts = group_voxels(keys)
        ref_rows, ref_inv, ref_counts = np.unique(keys, axis=0, return_inverse=True,
                                                  return_counts=True)
        assert np.array_equal(rows, ref_rows) and np.array_equal(counts, ref_counts)
        assert np.array_equal(inverse, ref_inv.reshape(-1)) and inverse.dtype == np.int64


def test_voxel_downsample_means():
    # Two points in voxel (0, 0, 0) and one in voxel (1, 0, 0) for a voxel size of 1.
    pts = np.array([[0.1, 0.2, 0.3], [0.5, 0.4, 0.1], [1.5, 0.5, 0.5]])
    desc = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 2.0]])
    colors = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.0], [0.2, 0.2, 0.2]])
    out = StructuredPointCloud(pts, desc, colors).voxel_downsample(1.0)
    assert len(out) == 2
    np.testing.assert_allclose(out.points, [[0.3, 0.3, 0.2], [1.5, 0.5, 0.5]])
    s = 1 / np.sqrt(2)
    np.testing.assert_allclose(out.descriptors, [[s, s], [0.0, 1.0]])  # re-normalised means
    np.testing.assert_allclose(out.colors, [[0.5, 0.25, 0.0], [0.2, 0.2, 0.2]])
    with pytest.raises(ValueError, match="voxel_size"):
        StructuredPointCloud(pts, desc).voxel_downsample(0.0)


def test_transform_and_open3d_round_trip():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(10, 3))
    desc = rng.normal(size=(10, 4))
    colors = rng.uniform(size=(10, 3))
    cloud = StructuredPointCloud(pts, desc, colors)
    T = make_transform(Rotation.from_rotvec([0.3, 0.2, -0.1]).as_matrix(), [0.5, 0.0, -1.0])
    moved = cloud.transform(T)
    np.testing.assert_allclose(moved.points, pts @ T[:3, :3].T + T[:3, 3])
    np.testing.assert_array_equal(moved.descriptors, desc)
    back = StructuredPointCloud.from_open3d(cloud.to_open3d(), descriptors=desc)
    np.testing.assert_allclose(back.points, pts)
    np.testing.assert_allclose(back.colors, colors)
    np.testing.assert_array_equal(back.descriptors, desc)
    assert StructuredPointCloud.from_open3d(cloud.to_open3d()).dim == 0
