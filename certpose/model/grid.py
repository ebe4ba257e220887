"""The scene grid: voxel states and the geometry that maps voxel indices to metres.

One definition shared by the scene field, the classifier and eq. (1)/(2), so none of them has to
import another to learn where a voxel is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.validation import as_float_array

__all__ = ["UNOBSERVED", "EMPTY", "OCCUPIED", "VOXEL_CENTRE_OFFSET", "GridSpec", "scene_grid_spec"]

# Scene voxel states (the values of ``SceneField.state``).
UNOBSERVED, EMPTY, OCCUPIED = 0, 1, 2

VOXEL_CENTRE_OFFSET = 0.5
"""Voxel ``(i, j, k)`` covers ``origin + [i, i+1) x [j, j+1) x [k, k+1)`` voxels: its centre is half a
voxel in."""


@dataclass(frozen=True)
class GridSpec:
    """Geometry of a scene grid: voxel ``(i, j, k)`` has its centre at ``origin + (idx + offset) * voxel_size``."""

    origin: NDArray[np.float64]
    voxel_size: float
    shape: tuple[int, int, int]
    offset: float

    def centres(self, index: ArrayLike) -> NDArray[np.float64]:
        """Centres (M, 3), metres, of the voxels ``index`` (M, 3); continuous indices map affinely."""
        return self.origin + (np.asarray(index, dtype=np.float64) + self.offset) * self.voxel_size

    def to_grid(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Continuous grid coordinates (N, 3) of ``points`` (N, 3); voxel centres map to integers."""
        return (points - self.origin) / self.voxel_size - self.offset

    def voxel_of(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        """Integer index (N, 3) of the voxel containing each point (possibly outside the grid)."""
        # Voxel i spans [i - 1/2, i + 1/2) in grid coordinates; no round trip through to_grid.
        return np.floor((points - self.origin) / self.voxel_size + (0.5 - self.offset)).astype(np.int64)

    def inside(self, index: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Whether each integer index (N, 3) lies in the grid."""
        return np.all((index >= 0) & (index < np.asarray(self.shape)), axis=-1)

    def axes(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Centre coordinates along x, y and z, shapes (X,), (Y,), (Z,) (a separable grid)."""
        return tuple(  # type: ignore[return-value]
            self.origin[a] + (np.arange(self.shape[a]) + self.offset) * self.voxel_size
            for a in range(3)
        )


def scene_grid_spec(scene: Any) -> GridSpec:
    """Read the grid geometry of a ``SceneField`` (voxel centres at ``origin + (idx + 0.5) * size``)."""
    origin = as_float_array(scene.origin, "scene.origin").reshape(3)
    vs = float(scene.voxel_size)
    if not (math.isfinite(vs) and vs > 0):
        raise ValueError(f"`scene.voxel_size` must be positive, got {vs}.")
    shape = tuple(int(s) for s in np.asarray(scene.state).shape)
    if len(shape) != 3:
        raise ValueError(f"Expected `scene.state` to have shape (X, Y, Z), got {shape}.")
    return GridSpec(origin, vs, shape, VOXEL_CENTRE_OFFSET)  # type: ignore[arg-type]
