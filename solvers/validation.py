"""Public argument checks shared by solvers and certpose (messages name the argument and shape)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "as_float_array",
    "check_points",
    "check_per_item",
    "check_rotation",
    "check_transform",
    "check_correspondences",
    "check_count",
    "check_limit",
    "resolve_rng",
]


def as_float_array(value: Any, name: str, *, allow_bool: bool = True,
                   copy: bool = True) -> NDArray[np.float64]:
    """Convert ``value`` to a float64 array, raising ``TypeError`` for non-numeric input.

    With ``allow_bool=False`` boolean arrays are refused too (a mask passed where coordinates
    belong would otherwise become 0/1 coordinates). With ``copy=False`` a float64 array is
    returned as it is (for callers that only read it).
    """
    if isinstance(value, (dict, set, str, bytes)) or value is None:
        raise TypeError(f"`{name}` must be a numeric array, got {type(value).__name__}.")
    try:
        arr = np.asarray(value)
    except Exception as exc:  # ragged lists and the like
        raise TypeError(f"`{name}` must be a numeric array, got {type(value).__name__}.") from exc
    kind = arr.dtype.kind  # (dtype kinds, not np.issubdtype: this runs on every small solve)
    if kind == "b" and not allow_bool:
        raise TypeError(f"`{name}` must be a numeric array, got dtype bool (a mask?); convert "
                        "it explicitly if 0/1 values are meant.")
    if kind == "c":
        raise TypeError(f"`{name}` must be real-valued, got dtype {arr.dtype}.")
    if kind not in "biuf":
        raise TypeError(f"`{name}` must be a numeric array, got dtype {arr.dtype}.")
    return np.array(arr, dtype=np.float64) if copy else np.asarray(arr, dtype=np.float64)


def check_points(value: Any, name: str, *, min_points: int = 1) -> NDArray[np.float64]:
    """Validate an ``(N, 3)`` array of finite points."""
    return _points_and_extent(value, name, min_points)[0]


def _points_and_extent(value: Any, name: str, min_points: int) -> tuple[NDArray[np.float64], float]:
    """:func:`check_points` and the largest absolute coordinate (0 when there are no points)."""
    arr = as_float_array(value, name, allow_bool=False)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"Expected `{name}` to have shape (N, 3), got {arr.shape}.")
    if arr.shape[0] < min_points:
        raise ValueError(
            f"Expected `{name}` to have at least {min_points} points, got {arr.shape[0]}."
        )
    if arr.shape[0] == 0:
        return arr, 0.0
    extent = float(np.abs(arr).max())  # NaN and inf make it non-finite: one pass checks both
    if not math.isfinite(extent):
        bad = int(np.count_nonzero(~np.isfinite(arr).all(axis=1)))
        raise ValueError(f"`{name}` contains NaN or inf values in {bad} row(s).")
    return arr, extent


def check_per_item(
    value: Any, name: str, n: int, *, positive: bool, allow_scalar: bool, allow_bool: bool = True
) -> NDArray[np.float64]:
    """Validate a scalar or ``(n,)`` array of finite, non-negative (or positive) values."""
    if type(value) is float and allow_scalar:  # the usual scalar: math is cheaper than numpy
        if not math.isfinite(value):
            raise ValueError(f"`{name}` contains NaN or inf values.")
        if value <= 0 if positive else value < 0:
            kind = "strictly positive" if positive else "non-negative"
            raise ValueError(f"`{name}` must be {kind}, got minimum {value:g}.")
        return np.full(n, value)
    arr = as_float_array(value, name, allow_bool=allow_bool)
    if arr.ndim == 0:
        if not allow_scalar:
            raise ValueError(f"Expected `{name}` to have shape ({n},), got a scalar.")
        arr = np.full(n, float(arr))
    elif arr.shape != (n,):
        shape = "a scalar or shape" if allow_scalar else "shape"
        raise ValueError(f"Expected `{name}` to have {shape} ({n},), got {arr.shape}.")
    if not np.isfinite(arr).all():
        raise ValueError(f"`{name}` contains NaN or inf values.")
    if positive and (arr <= 0).any():
        raise ValueError(f"`{name}` must be strictly positive, got minimum {arr.min():g}.")
    if not positive and (arr < 0).any():
        raise ValueError(f"`{name}` must be non-negative, got minimum {arr.min():g}.")
    return arr


def check_rotation(value: Any, name: str = "rotation", *, atol: float = 1e-6) -> NDArray[np.float64]:
    """Validate a 3x3 rotation matrix (orthonormal, determinant +1)."""
    arr = as_float_array(value, name, allow_bool=False)
    if arr.shape != (3, 3):
        raise ValueError(f"Expected `{name}` to have shape (3, 3), got {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"`{name}` contains NaN or inf values.")
    if not np.allclose(arr.T @ arr, np.eye(3), atol=atol) or np.linalg.det(arr) <= 0:
        raise ValueError(f"`{name}` is not a rotation matrix (orthonormal with det +1).")
    return arr


def check_transform(value: Any, name: str = "T", *, atol: float = 1e-6) -> NDArray[np.float64]:
    """Validate a 4x4 homogeneous rigid transform."""
    arr = as_float_array(value, name, allow_bool=False)
    if arr.shape != (4, 4):
        raise ValueError(f"Expected `{name}` to have shape (4, 4), got {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"`{name}` contains NaN or inf values.")
    if not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0], atol=atol):
        raise ValueError(f"The last row of `{name}` must be [0, 0, 0, 1], got {arr[3].tolist()}.")
    check_rotation(arr[:3, :3], f"{name}[:3, :3]", atol=atol)
    return arr


def check_count(value: Any, name: str, *, minimum: int = 0) -> int:
    """Validate an integer count (iterations, sizes): an ``int`` (not ``bool``) ``>= minimum``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"`{name}` must be an integer, got {value!r}.")
    if value < minimum:
        raise ValueError(f"`{name}` must be >= {minimum}, got {value}.")
    return int(value)


def check_limit(value: Any, name: str, *, allow_none: bool = True) -> float | None:
    """Validate a non-negative finite limit (e.g. a time limit in seconds), or ``None``."""
    if value is None and allow_none:
        return None
    if type(value) is float:  # the usual case: math is cheaper than numpy on one float
        if not math.isfinite(value) or value < 0:
            raise ValueError(f"`{name}` must be a non-negative finite number, got {value}.")
        return value
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise TypeError(f"`{name}` must be a number, got {value!r}.")
    if not np.isfinite(value) or value < 0:
        raise ValueError(f"`{name}` must be a non-negative finite number, got {value}.")
    return float(value)


def resolve_rng(rng: np.random.Generator | int | None) -> np.random.Generator:
    """Return a ``Generator`` from a seed, a generator or ``None``."""
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None or isinstance(rng, (int, np.integer)):
        return np.random.default_rng(rng)
    raise TypeError(f"`rng` must be a numpy Generator, an int or None, got {type(rng).__name__}.")


def check_correspondences(
    source: Any,
    target: Any,
    *,
    noise_bound: Any,
    weights: Any,
    cbar2: Any,
    min_n: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], float]:
    """Validate a weighted TLS problem's data; returns (source, target, beta, weights, cbar2).

    ``noise_bound`` is a positive scalar or (N,) array, ``weights`` None (all ones), a
    non-negative scalar or (N,) array, and ``cbar2`` a positive finite scalar.
    """
    return _check_correspondences(source, target, noise_bound, weights, cbar2, min_n)[:5]


def _check_correspondences(
    source: Any, target: Any, noise_bound: Any, weights: Any, cbar2: Any, min_n: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64],
           float, float]:
    """:func:`check_correspondences` and the largest absolute coordinate of the points."""
    src, extent_src = _points_and_extent(source, "source", 1)
    dst, extent_dst = _points_and_extent(target, "target", 1)
    extent = max(extent_src, extent_dst)
    if src.shape[0] != dst.shape[0]:
        raise ValueError(
            "Expected `source` and `target` to have the same number of rows, got "
            f"{src.shape[0]} and {dst.shape[0]}."
        )
    n = src.shape[0]
    if n < min_n:
        raise ValueError(f"Expected at least {min_n} correspondences, got {n}.")
    if noise_bound is None:
        raise ValueError("`noise_bound` is required (a positive scalar or an (N,) array).")
    beta = check_per_item(noise_bound, "noise_bound", n, positive=True, allow_scalar=True,
                          allow_bool=False)
    w = (
        np.ones(n)
        if weights is None
        else check_per_item(weights, "weights", n, positive=False, allow_scalar=True)
    )
    if type(cbar2) is float:  # the usual case
        if not (math.isfinite(cbar2) and cbar2 > 0):
            raise ValueError(f"`cbar2` must be a positive finite scalar, got {cbar2!r}.")
        return src, dst, beta, w, cbar2, extent
    c2 = as_float_array(cbar2, "cbar2")
    if c2.ndim != 0 or not np.isfinite(c2) or c2 <= 0:
        raise ValueError(f"`cbar2` must be a positive finite scalar, got {cbar2!r}.")
    return src, dst, beta, w, float(c2), extent
