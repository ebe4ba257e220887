"""The scene grid: voxel states and the geometry that maps voxel indices to metres.

One definition shared by the scene field, the classifier and eq. (1)/(2), so none of them has to
import another to learn where a voxel is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from solvers.validation import as_float_array

__all__ = ["UNOBSERVED", "EMPTY", "OCCUPIED", "GridSpec", "scene_grid_spec"]

# Scene voxel states (the values of ``SceneField.state``).
UNOBSERVED, EMPTY, OCCUPIED = 0, 1, 2


@dataclass(frozen=True)
class GridSpec:
    """Geometry of a scene grid: voxel ``(i, j, k)`` has its centre at ``origin + (idx + offset) * voxel_size``."""

    origin: NDArray[np.float64]
    voxel_size: float
    shape: tuple[int, int, int]
    offset: float

    def centres(self, index: NDArray[np.int64]) -> NDArray[np.float64]:
        """Centres (M, 3), metres, of the voxels ``index`` (M, 3)."""
        return self.origin + (np.asarray(index, dtype=np.float64) + self.offset) * self.voxel_size


def scene_grid_spec(scene: Any) -> GridSpec:
    """Read the grid geometry of a ``SceneField`` (voxel centres at ``origin + (idx + 0.5) * size``)."""
    origin = as_float_array(scene.origin, "scene.origin").reshape(3)
    vs = float(scene.voxel_size)
    if not (math.isfinite(vs) and vs > 0):
        raise ValueError(f"`scene.voxel_size` must be positive, got {vs}.")
    shape = tuple(int(s) for s in np.asarray(scene.state).shape)
    if len(shape) != 3:
        raise ValueError(f"Expected `scene.state` to have shape (X, Y, Z), got {shape}.")
    return GridSpec(origin, vs, shape, 0.5)  # type: ignore[arg-type]
