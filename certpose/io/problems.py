"""Registration problem files: one ``.npz`` per weighted TLS problem, read and written strictly.

Format (``numpy.savez``, no pickled objects):

``source``, ``target`` : (N, 3) float
    Corresponding points; row ``k`` of ``source`` matches row ``k`` of ``target``.
``weights`` : (N,) float
    Non-negative correspondence weights.
``noise_bounds`` : () or (N,) float
    Positive TLS inlier bound(s) ``beta``, in the units of the points.
``T_target_source`` : (4, 4) float, optional
    Ground truth (maps source points into the target frame).
``metadata`` : () str, optional
    A JSON object (e.g. ``suite``, ``name``, ``units``, ``rotation_tol_deg``,
    ``translation_tol``, ``symmetry_axis``).

``certpose register --problem FILE``, ``certpose bench --problems DIR`` and
``certpose pose --save-problem FILE`` use it. A malformed file raises :class:`ValueError`
with one line naming the file and the key.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["ProblemFile", "PROBLEM_KEYS", "load_problem", "save_problem"]

PROBLEM_KEYS = ("source", "target", "weights", "noise_bounds")
"""Keys every problem file holds."""
_OPTIONAL = ("T_target_source", "metadata")


@dataclass(frozen=True, eq=False)
class ProblemFile:
    """A weighted TLS registration problem with its optional ground truth.

    Attributes
    ----------
    source, target : (N, 3) ndarray
    weights : (N,) ndarray
    noise_bound : float or (N,) ndarray
        A float when the file holds one bound for all correspondences.
    T_target_source : (4, 4) ndarray or None
        Ground truth, when known.
    metadata : dict
        Free-form JSON-compatible description (``suite``, ``name``...).
    """

    source: NDArray[np.float64]
    target: NDArray[np.float64]
    weights: NDArray[np.float64]
    noise_bound: float | NDArray[np.float64]
    T_target_source: NDArray[np.float64] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def n(self) -> int:
        """Number of correspondences."""
        return int(self.source.shape[0])

    def outlier_ratio(self) -> float:
        """Fraction of correspondences whose ground-truth residual exceeds their bound (NaN
        without ground truth)."""
        if self.T_target_source is None:
            return float("nan")
        T = self.T_target_source
        r = np.linalg.norm(self.target - self.source @ T[:3, :3].T - T[:3, 3], axis=1)
        return float(np.mean(r > np.asarray(self.noise_bound)))


def _fail(path: Path, msg: str) -> ValueError:
    return ValueError(f"problem file '{path}': {msg}")


def _array(path: Path, key: str, value: Any, shape: tuple[int | None, ...]) -> NDArray[np.float64]:
    arr = np.asarray(value)
    if arr.dtype.kind not in "biuf":
        raise _fail(path, f"`{key}` must be numeric, got dtype {arr.dtype}.")
    arr = arr.astype(np.float64)
    if arr.ndim != len(shape) or any(
        s is not None and s != d for s, d in zip(shape, arr.shape, strict=True)
    ):
        dims = ", ".join("N" if s is None else str(s) for s in shape)
        want = f"({dims},)" if len(shape) == 1 else f"({dims})"
        raise _fail(path, f"expected `{key}` to have shape {want}, got {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise _fail(path, f"`{key}` contains NaN or inf values.")
    return arr


def _check(path: Path, data: dict[str, Any]) -> ProblemFile:
    missing = [k for k in PROBLEM_KEYS if k not in data]
    if missing:
        raise _fail(path, f"missing key(s) {', '.join(missing)} (a problem file holds "
                          f"{', '.join(PROBLEM_KEYS)} and optionally {', '.join(_OPTIONAL)}).")
    extra = sorted(set(data) - set(PROBLEM_KEYS) - set(_OPTIONAL))
    if extra:
        raise _fail(path, f"unexpected key(s) {', '.join(extra)}.")
    src = _array(path, "source", data["source"], (None, 3))
    n = src.shape[0]
    if n < 3:
        raise _fail(path, f"needs at least 3 correspondences, got {n}.")
    dst = _array(path, "target", data["target"], (n, 3))
    w = _array(path, "weights", data["weights"], (n,))
    if np.any(w < 0):
        raise _fail(path, "`weights` must be non-negative.")
    if not np.any(w > 0):
        raise _fail(path, "`weights` are all zero.")
    raw = np.asarray(data["noise_bounds"])
    beta = _array(path, "noise_bounds", raw, () if raw.ndim == 0 else (n,))
    if np.any(beta <= 0):
        raise _fail(path, "`noise_bounds` must be positive.")
    bound: float | NDArray[np.float64] = float(beta) if beta.ndim == 0 else beta
    T = None
    if "T_target_source" in data:
        T = _array(path, "T_target_source", data["T_target_source"], (4, 4))
        R = T[:3, :3]
        if not (np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
                and np.allclose(T[3], [0, 0, 0, 1])):
            raise _fail(path, "`T_target_source` is not a rigid transform (rotation block and "
                              "last row [0, 0, 0, 1]).")
    meta: dict[str, Any] = {}
    if "metadata" in data:
        m = np.asarray(data["metadata"])
        if m.dtype.kind != "U" or m.ndim != 0:
            raise _fail(path, "`metadata` must be one JSON string.")
        try:
            meta = json.loads(str(m))
        except json.JSONDecodeError as exc:
            raise _fail(path, f"`metadata` is not valid JSON ({exc.msg}).") from None
        if not isinstance(meta, dict):
            raise _fail(path, "`metadata` must be a JSON object.")
    return ProblemFile(src, dst, w, bound, T, meta)


def load_problem(path: str | os.PathLike[str]) -> ProblemFile:
    """Read and check a problem file.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    ValueError
        Not a ``.npz`` archive, a missing or unexpected key, a wrong shape, NaN/inf, negative
        weights, non-positive bounds, a ground truth that is not rigid, bad metadata.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"problem file '{p}' does not exist.")
    if not zipfile.is_zipfile(p):
        raise _fail(p, "not a .npz archive.")
    try:
        with np.load(p, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        raise _fail(p, f"not a readable .npz archive ({exc}).") from None
    except ValueError as exc:  # object arrays need pickle: refused
        raise _fail(p, f"cannot be read without pickle ({exc}).") from None
    return _check(p, data)


def save_problem(
    path: str | os.PathLike[str],
    source: ArrayLike,
    target: ArrayLike,
    *,
    noise_bound: float | ArrayLike,
    weights: ArrayLike | None = None,
    T_target_source: ArrayLike | None = None,
    metadata: dict[str, Any] | None = None,
) -> Path:
    """Write a problem file (checked as :func:`load_problem` would read it).

    Parameters
    ----------
    path : path
        Output file; ``.npz`` is required.
    source, target : (N, 3) array_like
    noise_bound : float or (N,) array_like
    weights : (N,) array_like, optional
        Default 1.
    T_target_source : (4, 4) array_like, optional
        Ground truth.
    metadata : dict, optional
        JSON-compatible (NaN becomes null).

    Returns
    -------
    Path
    """
    from certpose.io.output import to_json

    p = Path(path)
    if p.suffix != ".npz":
        raise ValueError(f"problem file '{p}' must end in .npz.")
    src = np.asarray(source, dtype=np.float64)
    data: dict[str, Any] = {
        "source": src,
        "target": np.asarray(target, dtype=np.float64),
        "weights": np.ones(src.shape[0]) if weights is None else np.asarray(weights, np.float64),
        "noise_bounds": np.asarray(noise_bound, dtype=np.float64),
    }
    if T_target_source is not None:
        data["T_target_source"] = np.asarray(T_target_source, dtype=np.float64)
    if metadata:
        data["metadata"] = np.asarray(to_json(metadata, indent=None))
    _check(p, data)  # never write a file load_problem would refuse
    from certpose.io.output import atomic_path

    try:
        with atomic_path(p) as tmp, tmp.open("wb") as fh:
            np.savez(fh, **data)
    except OSError as exc:
        raise OSError(f"cannot write problem file '{p}': {exc.strerror or exc}.") from None
    return p
