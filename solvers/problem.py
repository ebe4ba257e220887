"""The weighted truncated-least-squares (TLS) registration problem."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.validation import check_correspondences

__all__ = ["WeightedTLSProblem"]


class _derived:
    """A value computed from an instance on first access and then read from its ``__dict__``
    (``functools.cached_property`` without its lock, which Python 3.11 takes on every first
    access: a small solve makes a problem and reads each of these once)."""

    def __init__(self, fn: Any) -> None:
        self.fn = fn
        self.name = fn.__name__
        self.__doc__ = fn.__doc__

    def __get__(self, obj: Any, cls: Any = None) -> Any:
        if obj is None:
            return self
        value = self.fn(obj)
        obj.__dict__[self.name] = value
        return value


@dataclass(frozen=True, eq=False)
class WeightedTLSProblem:
    r"""Weighted TLS registration of corresponding point sets.

    The cost of a pose ``(R, t)`` is

    .. math:: f(R, t) = \sum_k w_k \min(\|b_k - R a_k - t\|^2 / \beta_k^2,\ \bar c^2)

    with ``a_k = source[k]``, ``b_k = target[k]``.

    Parameters
    ----------
    source : (N, 3) array_like
        Points ``a_k`` in the source frame.
    target : (N, 3) array_like
        Points ``b_k`` in the target frame; row ``k`` corresponds to ``source[k]``.
    weights : (N,) array_like or None, optional
        Non-negative weights ``w_k``; default 1.
    noise_bound : float or (N,) array_like
        Positive noise bounds ``beta_k`` (same units as the points).
    cbar2 : float, optional
        Truncation threshold ``cbar^2`` on normalised squared residuals; default 1.

    Raises
    ------
    ValueError
        Wrong shapes, mismatched lengths, fewer than 3 correspondences, NaN/inf,
        negative weights or non-positive noise bounds / ``cbar2``.
    TypeError
        Non-numeric input.
    """

    source: NDArray[np.float64]
    target: NDArray[np.float64]
    noise_bound: NDArray[np.float64] = field(default=None)  # type: ignore[assignment]
    weights: NDArray[np.float64] = field(default=None)  # type: ignore[assignment]
    cbar2: float = 1.0

    def __init__(
        self,
        source: ArrayLike,
        target: ArrayLike,
        *,
        noise_bound: ArrayLike,
        weights: ArrayLike | None = None,
        cbar2: float = 1.0,
    ) -> None:
        src, dst, beta, w, c2 = check_correspondences(
            source, target, noise_bound=noise_bound, weights=weights, cbar2=cbar2, min_n=3
        )
        self._set(src, dst, beta, w, c2)
        if weights is None:
            self.__dict__["_uniform_weights"] = True  # all ones

    @classmethod
    def _from_checked(
        cls,
        source: NDArray[np.float64],
        target: NDArray[np.float64],
        noise_bound: NDArray[np.float64],
        weights: NDArray[np.float64],
        cbar2: float,
    ) -> WeightedTLSProblem:
        """A problem from arrays derived from a validated problem (no second validation).

        For the library's own transformations of a checked problem (e.g. an exact rescaling):
        validation costs more than a small solve. The arrays must be float64, finite, of the
        right shapes, with positive ``noise_bound`` and non-negative ``weights``.
        """
        self = object.__new__(cls)
        self._set(source, target, noise_bound, weights, float(cbar2))
        return self

    def _set(self, src: NDArray[np.float64], dst: NDArray[np.float64],
             beta: NDArray[np.float64], w: NDArray[np.float64], c2: float) -> None:
        # The fields are read-only views; the compiled kernels take the arrays themselves
        # (their signatures are for writable arrays: a read-only input would be copied on
        # every call). The kernels never write into them.
        d = self.__dict__  # a frozen dataclass: its fields are set through the instance dict
        kernel = []
        for name, arr in (("source", src), ("target", dst), ("noise_bound", beta),
                          ("weights", w)):
            flags = arr.flags
            if not (flags.writeable and flags.c_contiguous):
                arr = np.array(arr, dtype=np.float64, order="C")
            kernel.append(arr)
            view = arr.view()
            view.flags.writeable = False
            d[name] = view
        d["cbar2"] = c2
        d["_kernel_arrays"] = tuple(kernel)

    @property
    def n(self) -> int:
        """Number of correspondences."""
        return int(self.source.shape[0])

    @property
    def scalar_noise_bound(self) -> bool:
        """True when every correspondence has the same noise bound."""
        return self._uniform_noise

    def residuals_sq(self, rotation: ArrayLike, translation: ArrayLike) -> NDArray[np.float64]:
        """Normalised squared residuals ``||b_k - R a_k - t||^2 / beta_k^2``, shape (N,)."""
        R = np.asarray(rotation, dtype=np.float64)
        t = np.asarray(translation, dtype=np.float64).reshape(3)
        d = self.target - self.source @ R.T - t
        d *= d
        return d.sum(axis=1) / self._beta2

    def residuals_sq_pair(
        self, rotation: ArrayLike, translation: ArrayLike, other_translation: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """:meth:`residuals_sq` of ``(R, t)`` and of ``(R, t')``, rotating the points once."""
        R = np.asarray(rotation, dtype=np.float64)
        moved = self.target - self.source @ R.T
        out = []
        for t in (translation, other_translation):
            d = moved - np.asarray(t, dtype=np.float64).reshape(3)
            d *= d
            out.append(d.sum(axis=1) / self._beta2)
        return out[0], out[1]

    def _residuals_sq_pair_t(
        self, moved: NDArray[np.float64], t: NDArray[np.float64], t_other: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], float, float]:
        """:meth:`residuals_sq_pair` from the rotated points ``moved`` = ``b_k - R a_k`` laid out
        as (3, N), and both TLS costs (both translations in each numpy call: small-N overhead)."""
        d = moved[None] - np.stack((t, t_other))[:, :, None]  # (2, 3, N)
        d *= d
        r2 = d.sum(axis=1)  # x + y + z in that order, as residuals_sq
        r2 /= self._beta2
        costs = np.minimum(r2, self.cbar2) @ self.weights
        return r2[0], r2[1], float(costs[0]), float(costs[1])

    # Derived arrays, computed once per problem and kept in the instance dict (a frozen
    # dataclass allows it; a problem's arrays never change).
    @_derived
    def _beta2(self) -> NDArray[np.float64]:
        return self.noise_bound**2

    @_derived
    def _inv_beta2(self) -> NDArray[np.float64]:
        """``1 / beta^2`` (N,), writable and C-contiguous (a kernel input)."""
        return 1.0 / self._beta2

    @_derived
    def _points_t(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``source.T`` and ``target.T`` (3, N), C-contiguous and writable (kernel inputs)."""
        return np.ascontiguousarray(self.source.T), np.ascontiguousarray(self.target.T)

    @_derived
    def _min_noise_bound(self) -> float:
        return float(self.noise_bound.min())

    @_derived
    def _uniform_noise(self) -> bool:
        """True when every correspondence has the same noise bound."""
        beta = self.noise_bound
        return bool((beta == beta[0]).all())

    @_derived
    def _uniform_weights(self) -> bool:
        """True when every weight is the same positive value."""
        w = self.weights
        wmin, wmax = float(w.min()), float(w.max())
        return wmin > 0.0 and not wmax - wmin > 1e-12 * wmax

    def cost(self, rotation: ArrayLike, translation: ArrayLike) -> float:
        """TLS cost of the pose ``(R, t)``."""
        return self.cost_from_residuals(self.residuals_sq(rotation, translation))

    def cost_from_residuals(self, r2: NDArray[np.float64]) -> float:
        """TLS cost given the normalised squared residuals ``r2`` (N,)."""
        return float(self.weights @ np.minimum(r2, self.cbar2))

    def inliers(self, rotation: ArrayLike, translation: ArrayLike) -> NDArray[np.bool_]:
        """Correspondences whose normalised squared residual is at most ``cbar2``."""
        return self.residuals_sq(rotation, translation) <= self.cbar2

    def subset(self, mask: ArrayLike) -> WeightedTLSProblem:
        """The problem restricted to the correspondences selected by ``mask`` (bool or index)."""
        idx = np.asarray(mask)
        return WeightedTLSProblem(
            self.source[idx],
            self.target[idx],
            noise_bound=self.noise_bound[idx],
            weights=self.weights[idx],
            cbar2=self.cbar2,
        )

    def __repr__(self) -> str:
        return f"WeightedTLSProblem(n={self.n}, cbar2={self.cbar2:g})"

    def __reduce__(self) -> tuple[Any, ...]:  # pickling (e.g. to a Dask worker)
        return (
            _rebuild,
            (self.source, self.target, self.noise_bound, self.weights, self.cbar2),
        )


def _rebuild(src: Any, dst: Any, beta: Any, w: Any, c2: float) -> WeightedTLSProblem:
    return WeightedTLSProblem(src, dst, noise_bound=beta, weights=w, cbar2=c2)
