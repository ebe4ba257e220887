"""Register two point files whose rows correspond (row k of SRC matches row k of DST).

Usage::

    python examples/register_two_files.py SRC DST --noise-bound B [--weights W]
    python examples/register_two_files.py            # writes and registers a demo pair

Files may be .npy, .csv/.txt, .xyz, .ply or .pcd. The demo pair is the Stanford bunny from
``../shared/data`` when it is there, else a synthetic shape, with 70% of the target rows
replaced by outliers; it is written as PLY files to a temporary folder first, so the example
goes through the same file readers as your own data.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

import certpose
from certpose.io import read_correspondences, read_weights

BUNNY = Path(__file__).resolve().parents[2] / "shared" / "data" / "bunny" / "bun_zipper_res3.ply"


def write_demo_pair(folder: Path, *, rng: np.random.Generator) -> tuple[Path, Path, np.ndarray]:
    """Write a source/target PLY pair with 70% outliers; return their paths and T_target_source."""
    import open3d as o3d

    from certpose.data.instances import make_instance
    from certpose.io import load_bunny, synthetic_shape
    from solvers.lie import make_transform

    cloud = load_bunny(BUNNY) if BUNNY.exists() else synthetic_shape(2000)
    inst = make_instance(cloud, 200, 0.7, noise=0.005, rng=rng)
    paths = []
    for name, pts in (("source.ply", inst.source), ("target.ply", inst.target)):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        o3d.io.write_point_cloud(str(folder / name), pcd, write_ascii=True)
        paths.append(folder / name)
    return paths[0], paths[1], make_transform(inst.rotation, inst.translation)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", nargs="?", help="source points file")
    parser.add_argument("target", nargs="?", help="target points file (same rows)")
    parser.add_argument("--noise-bound", type=float, help="inlier bound, units of the points")
    parser.add_argument("--weights", help="per-correspondence weights file")
    args = parser.parse_args()

    T_true = None
    with tempfile.TemporaryDirectory() as tmp:
        if args.source is None:
            src_path, dst_path, T_true = write_demo_pair(Path(tmp), rng=np.random.default_rng(0))
            noise_bound = 5.54 * 0.005
        else:
            if args.target is None or args.noise_bound is None:
                parser.error("give SRC DST --noise-bound B, or no arguments for the demo")
            src_path, dst_path, noise_bound = Path(args.source), Path(args.target), args.noise_bound
        source, target = read_correspondences(src_path, dst_path)
        weights = read_weights(args.weights, n=source.shape[0]) if args.weights else None

    result = certpose.register(source, target, noise_bound=noise_bound, weights=weights)
    print(f"status: {result.status.value} ({result.message})")
    print(f"inliers: {result.num_inliers} of {source.shape[0]}, TLS cost {result.cost:.4g}")
    print("T_target_source =")
    print(np.array2string(result.T_target_source, precision=4, suppress_small=True))
    if T_true is not None:
        from scipy.spatial.transform import Rotation

        R_err = Rotation.from_matrix(result.rotation.T @ T_true[:3, :3]).magnitude()
        t_err = np.linalg.norm(result.translation - T_true[:3, 3])
        print(f"error against the demo's ground truth: {np.degrees(R_err):.3f} deg, {t_err:.4f}")
    return 0 if result.success else 1


if __name__ == "__main__":
    sys.exit(main())
