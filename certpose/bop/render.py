"""Depth images of a triangle mesh seen by a pinhole camera (open3d's ray casting), for the VSD
metric and the visible fractions of converted datasets."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.validation import check_transform

__all__ = ["MeshDepthRenderer"]


class MeshDepthRenderer:
    """Renders z-depth images of one mesh (object frame) at given poses.

    The ray-casting structure is built once; each render moves the camera's rays into the
    object frame instead of moving the mesh.

    Parameters
    ----------
    vertices : (N, 3) array_like
        Object frame; the depth comes out in the same unit.
    faces : (M, 3) array_like of int
    """

    def __init__(self, vertices: ArrayLike, faces: ArrayLike) -> None:
        import open3d as o3d

        V = np.asarray(vertices, dtype=np.float32)
        F = np.asarray(faces, dtype=np.uint32)
        if V.ndim != 2 or V.shape[1] != 3:
            raise ValueError(f"Expected `vertices` to have shape (N, 3), got {V.shape}.")
        if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
            raise ValueError(f"Expected `faces` to have shape (M, 3) with M > 0, got {F.shape}.")
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(F))
        self._rays: dict[tuple[Any, ...], NDArray[np.float64]] = {}

    def _directions(self, K: NDArray[np.float64], shape: tuple[int, int]) -> NDArray[np.float64]:
        key = (*np.round(K.ravel(), 9), *shape)
        if key not in self._rays:
            h, w = shape
            v, u = np.mgrid[0:h, 0:w].astype(np.float64)
            # Pixel centres at integer coordinates, as the BOP toolkit's renderers.
            self._rays = {key: np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1],
                                         np.ones_like(u)], -1).reshape(-1, 3)}
        return self._rays[key]

    def depth(self, T_camera_object: ArrayLike, K: ArrayLike,
              shape: tuple[int, int]) -> NDArray[np.float64]:
        """The z-depth image (H, W) of the mesh at ``T_camera_object``; 0 where no surface.

        Parameters
        ----------
        T_camera_object : (4, 4) array_like
            Translation in the vertices' unit.
        K : (3, 3) array_like
            Intrinsic matrix, pixels.
        shape : (H, W)
        """
        import open3d as o3d

        T = check_transform(T_camera_object, "T_camera_object", atol=1e-4)
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        d_cam = self._directions(K, (int(shape[0]), int(shape[1])))
        R, t = T[:3, :3], T[:3, 3]
        # Rays in the object frame; directions keep unit camera z, so the hit is z-depth.
        origin = np.broadcast_to(-R.T @ t, d_cam.shape)
        rays = np.hstack([origin, d_cam @ R]).astype(np.float32)
        hit = self._scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        depth = np.where(np.isfinite(hit), hit.astype(np.float64), 0.0)
        return depth.reshape(int(shape[0]), int(shape[1]))
