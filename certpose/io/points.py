"""Reading point sets, correspondences and weights from files; built-in test shapes.

Supported point formats (chosen by the file suffix):

- ``.npy``: a float array of shape (N, 3);
- ``.csv``, ``.txt``: three numeric columns separated by commas or whitespace, with an
  optional header line and ``#`` comments;
- ``.xyz``: three whitespace-separated columns per line (e.g. YCB-Video's ``points.xyz``);
- ``.ply``: vertex positions read with ``plyfile``, which rejects truncated files;
- ``.pcd``: point clouds read with Open3D (positions only).

Every reader raises ``OSError`` (missing or unreadable file) or ``ValueError`` (empty,
unparsable, wrong shape, NaN/inf) with a one-line message naming the file.
"""

from __future__ import annotations

import logging
from os import PathLike
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "POINT_SUFFIXES",
    "WEIGHT_SUFFIXES",
    "read_mesh",
    "read_points",
    "read_correspondences",
    "read_weights",
    "load_bunny",
    "scale_to_unit_cube",
    "synthetic_shape",
]

log = logging.getLogger(__name__)

POINT_SUFFIXES = (".npy", ".csv", ".txt", ".xyz", ".ply", ".pcd")
WEIGHT_SUFFIXES = (".npy", ".csv", ".txt")

PathType = str | PathLike[str]


def _check_file(path: PathType, what: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{what} file '{p}' does not exist.")
    if not p.is_file():
        raise OSError(f"{what} file '{p}' is not a regular file.")
    return p


def _is_number_row(fields: list[str]) -> bool:
    try:
        [float(f) for f in fields]
    except ValueError:
        return False
    return True


def _read_text_table(p: Path, what: str, *, allow_header: bool) -> NDArray[np.float64]:
    """Parse a comma- or whitespace-separated numeric table (optional first header line)."""
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{what} file '{p}' is not a text file (cannot decode it as UTF-8).") from None
    except OSError as exc:
        raise OSError(f"cannot read {what} file '{p}': {exc.strerror or exc}.") from None
    lines = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines:
        raise ValueError(f"{what} file '{p}' is empty (no data rows).")
    delimiter = "," if "," in lines[-1] else None

    def fields(line: str) -> list[str]:
        return [f.strip() for f in line.split(delimiter)]

    if allow_header and not _is_number_row(fields(lines[0])):
        lines = lines[1:]  # a header line such as "x,y,z"
        if not lines:
            raise ValueError(f"{what} file '{p}' has a header but no data rows.")
    try:
        table = np.loadtxt(lines, delimiter=delimiter, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        first = str(exc).splitlines()[0] if str(exc) else "malformed rows"
        raise ValueError(f"cannot parse {what} file '{p}' as a numeric table: {first}") from None
    return table


def _read_npy(p: Path, what: str) -> NDArray[np.float64]:
    try:
        arr = np.load(p, allow_pickle=False)
    except OSError as exc:
        raise OSError(f"cannot read {what} file '{p}': {exc.strerror or exc}.") from None
    except (ValueError, EOFError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else "truncated or not in .npy format"
        raise ValueError(f"{what} file '{p}' is not a valid .npy array: {reason}") from None
    if not isinstance(arr, np.ndarray):
        raise ValueError(f"{what} file '{p}' does not hold a single array.")
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        # Booleans too: a saved mask is not coordinates or weights.
        raise ValueError(f"{what} file '{p}' holds a non-numeric array (dtype {arr.dtype}).")
    return np.asarray(arr, dtype=np.float64)


def _read_ply(p: Path, what: str) -> NDArray[np.float64]:
    from plyfile import PlyData, PlyParseError

    # plyfile checks the header's element counts against the body, so a truncated file is an
    # error rather than uninitialised rows.
    try:
        ply = PlyData.read(str(p))
    except PlyParseError as exc:
        raise ValueError(f"{what} file '{p}' is not a valid PLY file: {exc}") from None
    except (ValueError, EOFError, IndexError, UnicodeDecodeError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else "truncated or malformed"
        raise ValueError(f"{what} file '{p}' is not a valid PLY file: {reason}") from None
    except OSError as exc:
        raise OSError(f"cannot read {what} file '{p}': {exc.strerror or exc}.") from None
    if "vertex" not in ply:
        raise ValueError(f"{what} file '{p}' has no 'vertex' element.")
    vertex = ply["vertex"].data
    names = vertex.dtype.names or ()
    if not all(axis in names for axis in "xyz"):
        raise ValueError(f"{what} file '{p}' has no x, y, z vertex properties (found {names}).")
    return np.column_stack([np.asarray(vertex[axis], dtype=np.float64) for axis in "xyz"])


_PCD_KEYS = ("FIELDS", "SIZE", "COUNT", "POINTS", "DATA")


def _check_pcd(p: Path, what: str) -> int:
    """Check a PCD file's header against its body; the number of points it declares.

    Open3D reads a truncated ASCII body as uninitialised rows and a header without ``POINTS``
    as a huge allocation, so both are refused here first.
    """
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise OSError(f"cannot read {what} file '{p}': {exc.strerror or exc}.") from None

    def bad(reason: str) -> ValueError:
        return ValueError(f"{what} file '{p}' is not a valid PCD file: {reason}")

    header: dict[str, list[str]] = {}
    pos = 0
    while "DATA" not in header:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise bad("the header has no DATA line.")
        line = raw[pos:end].decode("ascii", errors="replace").split("#", 1)[0].split()
        pos = end + 1
        if line:
            header[line[0].upper()] = line[1:]
    missing = [k for k in _PCD_KEYS if k not in header]
    if missing:
        raise bad(f"the header has no {', '.join(missing)} line.")
    fields = header["FIELDS"]
    if not all(axis in fields for axis in "xyz"):
        raise bad(f"no x, y, z fields (found {' '.join(fields)}).")
    try:
        n = int(header["POINTS"][0])
        row_bytes = sum(int(s) * int(c) for s, c in zip(header["SIZE"], header["COUNT"],
                                                        strict=True))
    except (ValueError, IndexError):
        raise bad("malformed POINTS, SIZE or COUNT line.") from None
    if n < 0 or len(header["SIZE"]) != len(fields):
        raise bad("malformed POINTS, SIZE or COUNT line.")
    body = raw[pos:]
    kind = (header["DATA"] or [""])[0].lower()
    if kind == "ascii":
        rows = [ln.split() for ln in body.splitlines() if ln.split(b"#", 1)[0].strip()]
        if len(rows) < n:
            raise bad(f"truncated: the header declares {n} points, the body holds {len(rows)} "
                      "rows.")
        values = sum(int(c) for c in header["COUNT"])
        short = next((k for k, r in enumerate(rows[:n]) if len(r) != values), None)
        if short is not None:
            raise bad(f"row {short + 1} of the body holds {len(rows[short])} values, not "
                      f"{values}.")
    elif kind == "binary":
        if len(body) < n * row_bytes:
            raise bad(f"truncated: {n} points of {row_bytes} bytes need {n * row_bytes} bytes, "
                      f"the body holds {len(body)}.")
    elif kind == "binary_compressed":
        size = int.from_bytes(body[:4], "little") if len(body) >= 4 else -1
        if size < 0 or len(body) < 8 + size:
            raise bad("truncated compressed body.")
    else:
        raise bad(f"unknown DATA type {kind!r}.")
    return n


def _read_open3d(p: Path, what: str) -> NDArray[np.float64]:
    import open3d as o3d  # heavy: imported on demand

    declared = _check_pcd(p, what) if p.suffix.lower() == ".pcd" else None
    # Open3D reports read failures as console warnings and an empty cloud; silence the
    # warning and raise instead.
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(str(p))
    pts = np.asarray(cloud.points, dtype=np.float64)
    if pts.shape[0] == 0:
        raise ValueError(
            f"{what} file '{p}' holds no points (empty, or not a valid {p.suffix} point cloud)."
        )
    if declared is not None and pts.shape[0] != declared:
        raise ValueError(f"{what} file '{p}' declares {declared} points but {pts.shape[0]} "
                         "were read.")
    return pts.reshape(-1, 3)


def _finite_rows(arr: NDArray[np.float64], p: Path, what: str) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        rows = int(np.count_nonzero(bad.reshape(arr.shape[0], -1).any(axis=1)))
        raise ValueError(f"{what} file '{p}' contains NaN or inf values in {rows} row(s).")


def read_points(path: PathType, *, name: str = "points") -> NDArray[np.float64]:
    """Read an ``(N, 3)`` point array from a file.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.npy``, ``.csv``/``.txt``, ``.xyz``, ``.ply`` or ``.pcd`` file.
    name : str, optional
        What the points are (used in error messages), e.g. ``"source"``.

    Returns
    -------
    (N, 3) ndarray of float64
        The points, one per row, in the file's units.

    Raises
    ------
    OSError
        The file is missing or unreadable.
    ValueError
        Unknown suffix, empty or unparsable file, shape other than (N, 3), NaN or inf.
    """
    p = _check_file(path, name)
    suffix = p.suffix.lower()
    if suffix == ".npy":
        arr = _read_npy(p, name)
    elif suffix in (".csv", ".txt"):
        arr = _read_text_table(p, name, allow_header=True)
    elif suffix == ".xyz":
        arr = _read_text_table(p, name, allow_header=False)
    elif suffix == ".ply":
        arr = _read_ply(p, name)
    elif suffix == ".pcd":
        arr = _read_open3d(p, name)
    else:
        raise ValueError(
            f"{name} file '{p}' has unsupported suffix {p.suffix!r}; "
            f"expected one of {', '.join(POINT_SUFFIXES)}."
        )
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"Expected {name} file '{p}' to have shape (N, 3), got {arr.shape}.")
    if arr.shape[0] == 0:
        raise ValueError(f"{name} file '{p}' holds no points.")
    _finite_rows(arr, p, name)
    return np.ascontiguousarray(arr)


#: Suffixes :func:`read_mesh` reads triangles from.
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off")


def read_mesh(path: PathType, *, name: str = "model") -> tuple[NDArray[np.float64], NDArray[np.int64]] | None:
    """Read a triangle mesh (vertices and triangles) from a ``.ply``, ``.obj``, ``.stl`` or
    ``.off`` file, as object models often ship (BOP's ``models/*.ply``).

    Returns
    -------
    vertices : (V, 3) ndarray of float64
        In the file's units.
    triangles : (F, 3) ndarray of int64
    None
        When the file holds no triangles (a point cloud: read it with :func:`read_points`) or
        has another suffix.

    Raises
    ------
    OSError
        The file is missing or unreadable.
    ValueError
        NaN or inf vertices, or triangles that index no vertex.
    """
    p = _check_file(path, name)
    if p.suffix.lower() not in MESH_SUFFIXES:
        return None
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(p), print_progress=False)
    V = np.asarray(mesh.vertices, dtype=np.float64).copy()
    F = np.asarray(mesh.triangles, dtype=np.int64).copy()
    if F.shape[0] == 0:
        return None
    _finite_rows(V, p, name)
    if F.min() < 0 or F.max() >= V.shape[0]:
        raise ValueError(f"{name} file '{p}' has triangles that index no vertex.")
    return V, F


def read_correspondences(
    source_path: PathType, target_path: PathType
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Read corresponding point sets: row ``k`` of the source matches row ``k`` of the target.

    Returns
    -------
    source, target : (N, 3) ndarray of float64

    Raises
    ------
    OSError, ValueError
        As :func:`read_points`, and ``ValueError`` when the row counts differ.
    """
    src = read_points(source_path, name="source")
    dst = read_points(target_path, name="target")
    if src.shape[0] != dst.shape[0]:
        raise ValueError(
            f"source file '{source_path}' has {src.shape[0]} points but target file "
            f"'{target_path}' has {dst.shape[0]}; row k of each must correspond."
        )
    return src, dst


def read_weights(path: PathType, *, n: int | None = None) -> NDArray[np.float64]:
    """Read non-negative correspondence weights, shape ``(N,)``.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.npy`` array of shape (N,) or (N, 1), or a ``.csv``/``.txt`` file with one value
        per line (optional header line).
    n : int, optional
        The expected number of weights (the number of correspondences).

    Returns
    -------
    (N,) ndarray of float64

    Raises
    ------
    OSError, ValueError
        Missing/unreadable file, wrong shape or length, NaN/inf or negative values.
    """
    p = _check_file(path, "weights")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        arr = _read_npy(p, "weights")
    elif suffix in (".csv", ".txt"):
        arr = _read_text_table(p, "weights", allow_header=True)
    else:
        raise ValueError(
            f"weights file '{p}' has unsupported suffix {p.suffix!r}; "
            f"expected one of {', '.join(WEIGHT_SUFFIXES)}."
        )
    if arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]
    if arr.ndim != 1:
        raise ValueError(f"Expected weights file '{p}' to have shape (N,), got {arr.shape}.")
    if arr.shape[0] == 0:
        raise ValueError(f"weights file '{p}' holds no values.")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"Expected weights file '{p}' to have shape ({n},), got {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"weights file '{p}' contains NaN or inf values.")
    if np.any(arr < 0):
        raise ValueError(f"weights file '{p}' holds negative weights (minimum {arr.min():g}).")
    return np.ascontiguousarray(arr)


def scale_to_unit_cube(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Centre ``points`` (N, 3) on their bounding box and scale them to fit ``[-0.5, 0.5]^3``.

    The largest bounding-box side becomes 1, so the shape keeps its aspect ratio.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"Expected `points` to have shape (N, 3), got {pts.shape}.")
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    extent = float(np.max(hi - lo))
    if not extent > 0:
        raise ValueError("`points` are all coincident; they cannot be scaled into the unit cube.")
    return (pts - (lo + hi) / 2.0) / extent


def load_bunny(path: PathType) -> NDArray[np.float64]:
    """Load the Stanford bunny (or any point file) scaled into the unit cube.

    This is the shape of the TEASER++/QUASAR benchmark protocol: vertex positions centred on
    their bounding box and scaled so that the largest side is 1 (inside ``[-0.5, 0.5]^3``).

    Parameters
    ----------
    path : str or os.PathLike
        E.g. ``../shared/data/bunny/bun_zipper_res3.ply``; any format of :func:`read_points`.

    Returns
    -------
    (N, 3) ndarray of float64
        Dimensionless points in the unit cube.
    """
    return scale_to_unit_cube(read_points(path, name="bunny"))


def synthetic_shape(n_points: int = 2000) -> NDArray[np.float64]:
    """A deterministic, non-symmetric 3-D surface, scaled into the unit cube.

    A lumpy ellipsoid: a Fibonacci lattice on the sphere, anisotropically scaled, with radial
    Gaussian bumps at fixed, irregular directions, so that no rotation maps it onto itself.
    It is the default shape of ``certpose bench`` and ``certpose register --demo`` (no data
    file needed). The same ``n_points`` always gives the same points.

    Parameters
    ----------
    n_points : int, optional
        Number of surface points (>= 10).

    Returns
    -------
    (n_points, 3) ndarray of float64
        Dimensionless points inside ``[-0.5, 0.5]^3``.
    """
    if int(n_points) != n_points or n_points < 10:
        raise ValueError(f"`n_points` must be an integer >= 10, got {n_points!r}.")
    n = int(n_points)
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5.0**0.5) * k
    rho = np.sqrt(1.0 - z * z)
    u = np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])
    # Bumps at irregular directions with distinct heights and widths break every symmetry.
    centres = np.array(
        [[0.9, 0.3, 0.2], [-0.2, 0.8, 0.5], [0.1, -0.4, 0.9], [-0.7, -0.6, -0.3], [0.3, 0.1, -0.95]]
    )
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    heights = np.array([0.55, 0.35, 0.25, 0.4, 0.15])
    widths = np.array([0.25, 0.35, 0.2, 0.3, 0.15])
    cos_ang = u @ centres.T
    radius = 1.0 + (heights * np.exp(-(1.0 - cos_ang) / widths**2 * 2.0)).sum(axis=1)
    radius += 0.05 * np.sin(3.0 * phi) * z  # fine ripple
    pts = u * radius[:, None] * np.array([1.0, 0.7, 0.5])
    return scale_to_unit_cube(pts)
