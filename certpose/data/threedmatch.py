"""A real indoor scan pair (3DMatch-style) and putative FPFH correspondences on it.

The pair lives in ``../shared/data/3dmatch`` (``src.npy`` (M, 3), ``ref.npy`` (K, 3) in metres,
``gt.npy`` the 4x4 transform mapping ``src`` into ``ref``'s frame). Putative correspondences are
made the way TEASER++'s 3DMatch example makes them: voxel downsampling, normals, open3d's FPFH
features, mutual nearest neighbours in feature space. Real features give dense
pairwise-consistency graphs (many outliers consistent with each other), which is what this
module is for: a benchmark of the solvers on them (``examples/benchmarks/bench_dense.py``, the bench
suites).

At the defaults (``voxel_size=0.045``) the pair gives 940 correspondences, about 90 of them
within 0.1 m of ground truth; with ``noise_bound=NOISE_BOUND`` their consistency graph has about
53,000 edges.

Any two scans in point-cloud files (``.ply``, ``.pcd``, ``.npy``, ...) get the same treatment
with :func:`scan_correspondences`, whose default voxel (``TEASER_VOXEL_SIZE``, 0.05 m) is that
of TEASER++'s Python FPFH example: its ``cloud_bin_0.ply -> cloud_bin_4.ply`` pair (3DMatch's
``7-scenes-redkitchen`` fragments) gives 981 correspondences. A 3DMatch ground truth file
(``gt.log``) is read by :func:`read_threedmatch_log`.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from certpose.io.points import read_points
from solvers.lie import make_transform, project_to_so3
from solvers.validation import check_points, check_transform

__all__ = [
    "NOISE_BOUND",
    "TEASER_VOXEL_SIZE",
    "ScanPair",
    "Correspondences",
    "default_threedmatch_dir",
    "load_threedmatch_pair",
    "fpfh_correspondences",
    "threedmatch_correspondences",
    "scan_correspondences",
    "read_threedmatch_log",
    "threedmatch_log_pose",
]

log = logging.getLogger(__name__)

PathType = str | os.PathLike
NOISE_BOUND = 0.05
"""Noise bound ``beta`` in metres for the pair's correspondences (TEASER++'s 3DMatch example)."""

TEASER_VOXEL_SIZE = 0.05
"""Voxel size in metres of TEASER++'s Python FPFH example (also its noise bound)."""

_FILES = ("src.npy", "ref.npy", "gt.npy")


@dataclass(frozen=True)
class ScanPair:
    """Two partly overlapping scans and the transform between them.

    Attributes
    ----------
    source : (M, 3) ndarray
        Source scan, metres.
    target : (K, 3) ndarray
        Target scan, metres.
    T_target_source : (4, 4) ndarray
        Ground truth: maps source points into the target frame.
    """

    source: NDArray[np.float64]
    target: NDArray[np.float64]
    T_target_source: NDArray[np.float64]


@dataclass(frozen=True)
class Correspondences:
    """Putative correspondences with ground truth: row ``k`` of ``source`` matches row ``k`` of
    ``target``.

    Attributes
    ----------
    source, target : (N, 3) ndarray
        Matched points (metres), downsampled-scan points.
    T_target_source : (4, 4) ndarray or None
        Ground truth pose mapping source points into the target frame; ``None`` when there is
        none.
    voxel_size : float
        The voxel size (metres) the scans were downsampled with.
    """

    source: NDArray[np.float64]
    target: NDArray[np.float64]
    T_target_source: NDArray[np.float64] | None
    voxel_size: float

    @property
    def n(self) -> int:
        """Number of correspondences."""
        return int(self.source.shape[0])

    def residuals(self) -> NDArray[np.float64]:
        """Ground-truth residuals ``|T source_k - target_k|`` in metres, shape (N,).

        Raises
        ------
        ValueError
            When there is no ground truth (``T_target_source`` is ``None``).
        """
        T = self.T_target_source
        if T is None:
            raise ValueError("These correspondences have no ground truth (`T_target_source` is None).")
        return np.linalg.norm(self.source @ T[:3, :3].T + T[:3, 3] - self.target, axis=1)


def default_threedmatch_dir() -> Path:
    """``../shared/data/3dmatch`` beside the repository (as the tests find their data), else the
    same relative to the working directory."""
    beside_repo = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "3dmatch"
    if beside_repo.is_dir():
        return beside_repo
    return Path("..") / "shared" / "data" / "3dmatch"


def load_threedmatch_pair(path: PathType | None = None) -> ScanPair:
    """Load the scan pair ``src.npy``, ``ref.npy``, ``gt.npy`` from a folder.

    Parameters
    ----------
    path : str, os.PathLike or None
        The folder (default :func:`default_threedmatch_dir`, ``../shared/data/3dmatch``).

    Returns
    -------
    ScanPair

    Raises
    ------
    FileNotFoundError
        When the folder or one of its three files is missing.
    ValueError
        On malformed arrays (shapes, NaN, a ground truth that is not a rigid transform).
    """
    folder = default_threedmatch_dir() if path is None else Path(path)
    if not folder.is_dir():
        raise FileNotFoundError(
            f"3DMatch pair folder '{folder}' does not exist (expected {', '.join(_FILES)}; "
            "the project's copy is ../shared/data/3dmatch beside the repository)."
        )
    missing = [f for f in _FILES if not (folder / f).is_file()]
    if missing:
        raise FileNotFoundError(f"3DMatch pair folder '{folder}' lacks {', '.join(missing)}.")
    source = read_points(folder / "src.npy", name="source scan")
    target = read_points(folder / "ref.npy", name="target scan")
    try:
        gt = np.load(folder / "gt.npy", allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"cannot read ground truth '{folder / 'gt.npy'}': {exc}") from None
    T = check_transform(np.asarray(gt, dtype=np.float64), "gt.npy", atol=1e-3)
    # The file's rotation is orthonormal to ~1e-4 only (saved in single precision): project it.
    T = make_transform(project_to_so3(T[:3, :3]), T[:3, 3])
    return ScanPair(source=source, target=target, T_target_source=T)


def _fpfh(points: NDArray[np.float64], voxel_size: float) -> tuple[NDArray, NDArray]:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(points)))
    cloud = cloud.voxel_down_sample(voxel_size)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel_size, max_nn=30))
    feat = o3d.pipelines.registration.compute_fpfh_feature(
        cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel_size, max_nn=100)
    )
    return np.asarray(cloud.points, dtype=np.float64), np.asarray(feat.data, dtype=np.float64).T


def fpfh_correspondences(
    source: NDArray[np.float64], target: NDArray[np.float64], *, voxel_size: float = 0.045
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Putative correspondences between two scans: mutual nearest FPFH neighbours.

    Each scan is voxel-downsampled (``voxel_size``), normals are estimated within
    ``2 voxel_size`` (30 neighbours at most), open3d's 33-bin FPFH within ``5 voxel_size``
    (100 at most); a pair ``(i, j)`` is kept when ``j`` is ``i``'s nearest target feature and
    ``i`` is ``j``'s nearest source feature. Deterministic (no sampling).

    Parameters
    ----------
    source : (M, 3) array_like
        Source scan, metres.
    target : (K, 3) array_like
        Target scan, metres.
    voxel_size : float
        Downsampling voxel in metres (default 0.045).

    Returns
    -------
    source, target : (N, 3) ndarray
        Matched points, sorted by source point index of the downsampled source scan.
    """
    from scipy.spatial import cKDTree

    src = check_points(source, "source", min_points=2)
    tgt = check_points(target, "target", min_points=2)
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise ValueError(f"`voxel_size` must be positive, got {voxel_size}.")
    ps, fs = _fpfh(src, float(voxel_size))
    pt, ft = _fpfh(tgt, float(voxel_size))
    if ps.shape[0] < 1 or pt.shape[0] < 1:
        raise ValueError(f"`voxel_size` {voxel_size} leaves no points to describe.")
    to_target = cKDTree(ft).query(fs)[1]
    to_source = cKDTree(fs).query(ft)[1]
    mutual = np.flatnonzero(to_source[to_target] == np.arange(fs.shape[0]))
    log.debug("FPFH: %d and %d downsampled points, %d mutual matches",
              ps.shape[0], pt.shape[0], mutual.size)
    return ps[mutual], pt[to_target[mutual]]


def threedmatch_correspondences(
    path: PathType | None = None, *, voxel_size: float = 0.045
) -> Correspondences:
    """Putative FPFH correspondences on the 3DMatch pair, with its ground truth.

    Parameters
    ----------
    path : str, os.PathLike or None
        Folder of the pair (default ``../shared/data/3dmatch``, see
        :func:`load_threedmatch_pair`).
    voxel_size : float
        Downsampling voxel in metres (see :func:`fpfh_correspondences`).

    Returns
    -------
    Correspondences
        Register them with ``noise_bound=NOISE_BOUND`` (0.05 m).
    """
    pair = load_threedmatch_pair(path)
    src, tgt = fpfh_correspondences(pair.source, pair.target, voxel_size=voxel_size)
    return Correspondences(
        source=src, target=tgt, T_target_source=pair.T_target_source, voxel_size=float(voxel_size)
    )


def scan_correspondences(
    source_file: PathType,
    target_file: PathType,
    *,
    voxel_size: float = TEASER_VOXEL_SIZE,
    T_target_source: NDArray[np.float64] | None = None,
) -> Correspondences:
    """Putative FPFH correspondences between two scans read from point-cloud files.

    The files are read with :func:`certpose.io.points.read_points` (``.ply``, ``.pcd``,
    ``.npy``, ``.csv``/``.txt``, ``.xyz``; positions only) and matched by
    :func:`fpfh_correspondences`: voxel downsampling, normals within ``2 voxel_size``, open3d's
    FPFH within ``5 voxel_size``, mutual nearest neighbours in feature space. At the default
    voxel (0.05 m) this is what TEASER++'s Python FPFH example does; on its
    ``cloud_bin_0.ply -> cloud_bin_4.ply`` pair it gives 981 correspondences, as there. Register
    them with a noise bound of about the voxel size (TEASER++'s example uses 0.05 m).

    Parameters
    ----------
    source_file, target_file : str or os.PathLike
        The source and target scans, coordinates in metres.
    voxel_size : float, optional
        Downsampling voxel in metres (default ``TEASER_VOXEL_SIZE``, 0.05).
    T_target_source : (4, 4) array_like or None, optional
        A ground truth mapping source points into the target frame, kept in the result (its
        rotation is projected onto SO(3); orthonormality to 1e-3 is required, as 3DMatch's
        ``gt.log`` files hold 9 digits). ``None``: no ground truth.

    Returns
    -------
    Correspondences
        ``source``, ``target`` (N, 3): matched points of the downsampled scans, sorted by
        downsampled source index; ``T_target_source`` as given (or ``None``).

    Raises
    ------
    FileNotFoundError
        When a file does not exist.
    ValueError
        On an unreadable, empty or non-finite cloud, an unknown suffix, a non-positive
        ``voxel_size`` or a ground truth that is not a rigid transform.

    Examples
    --------
    >>> corr = scan_correspondences("cloud_bin_0.ply", "cloud_bin_4.ply")  # doctest: +SKIP
    >>> corr.n  # doctest: +SKIP
    981
    """
    T = None
    if T_target_source is not None:
        T = check_transform(np.asarray(T_target_source, dtype=np.float64), "T_target_source",
                            atol=1e-3)
        T = make_transform(project_to_so3(T[:3, :3]), T[:3, 3])
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise ValueError(f"`voxel_size` must be positive, got {voxel_size}.")
    source = read_points(source_file, name="source scan")
    target = read_points(target_file, name="target scan")
    src, tgt = fpfh_correspondences(source, target, voxel_size=voxel_size)
    log.info("FPFH: %d correspondences between '%s' and '%s' (voxel %g m)", src.shape[0],
             source_file, target_file, voxel_size)
    return Correspondences(source=src, target=tgt, T_target_source=T, voxel_size=float(voxel_size))


def read_threedmatch_log(path: PathType) -> dict[tuple[int, int], NDArray[np.float64]]:
    """Read a 3DMatch ground-truth file (``gt.log``): the pose of each listed fragment pair.

    The file holds blocks of 5 lines: ``i j n`` (two fragment indices and the number of
    fragments), then a 4x4 matrix. Entry ``(i, j)`` maps the points of fragment ``j``
    (``cloud_bin_j``) into the frame of fragment ``i``; so for ``source = cloud_bin_i``,
    ``target = cloud_bin_j``, ``T_target_source`` is its inverse (see
    :func:`threedmatch_log_pose`).

    Parameters
    ----------
    path : str or os.PathLike
        The ``gt.log`` file.

    Returns
    -------
    dict
        ``(i, j) -> (4, 4) ndarray`` as in the file, the rotation projected onto SO(3) (the
        files hold 9 digits: orthonormal to about 1e-4).

    Raises
    ------
    FileNotFoundError
        When the file does not exist.
    ValueError
        When a block is malformed or a matrix is not a rigid transform (to 1e-3).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"3DMatch log file '{p}' does not exist.")
    lines = [ln.strip() for ln in p.read_text(encoding="utf-8").splitlines() if ln.strip()]
    if not lines or len(lines) % 5:
        raise ValueError(f"3DMatch log file '{p}' must hold blocks of 5 non-empty lines (a header "
                         f"'i j n' and 4 matrix rows), got {len(lines)} lines.")
    out: dict[tuple[int, int], NDArray[np.float64]] = {}
    for b in range(0, len(lines), 5):
        try:
            head = [int(v) for v in lines[b].split()]
            M = np.array([[float(v) for v in ln.split()] for ln in lines[b + 1:b + 5]])
        except ValueError:
            raise ValueError(f"3DMatch log file '{p}': malformed block at line {b + 1}.") from None
        if len(head) != 3 or M.shape != (4, 4):
            raise ValueError(f"3DMatch log file '{p}': malformed block at line {b + 1} (expected "
                             "'i j n' and four rows of 4 numbers).")
        T = check_transform(M, f"the pose at line {b + 1} of '{p}'", atol=1e-3)
        out[(head[0], head[1])] = make_transform(project_to_so3(T[:3, :3]), T[:3, 3])
    return out


def threedmatch_log_pose(path: PathType, source_index: int, target_index: int) -> NDArray[np.float64]:
    """``T_target_source`` from a 3DMatch ``gt.log`` for ``cloud_bin_<source_index>`` to
    ``cloud_bin_<target_index>``.

    Parameters
    ----------
    path : str or os.PathLike
        The ``gt.log`` file (see :func:`read_threedmatch_log`).
    source_index, target_index : int
        Fragment indices of the source and target scans.

    Returns
    -------
    (4, 4) ndarray
        Maps source points into the target frame.

    Raises
    ------
    KeyError
        When the file lists neither ``(source, target)`` nor ``(target, source)``.
    """
    entries = read_threedmatch_log(path)
    if (source_index, target_index) in entries:
        return np.linalg.inv(entries[(source_index, target_index)])
    if (target_index, source_index) in entries:
        return entries[(target_index, source_index)]
    raise KeyError(f"3DMatch log file '{path}' lists no pose for fragments {source_index} and "
                   f"{target_index}.")
