r"""Which object points a camera sees at a pose: eq. (1) scores only those.

The paper's eq. (1) sums over every object point. Points that the object itself hides from the
camera at a pose (its back, a handle behind its body) carry no evidence for or against that pose,
yet they vote: each one that lands in unobserved space pays the unobserved prior, each one that
lands on an observed surface behind the object earns a match. On YCB-Video frames the 180-degree
flips of boxes and bottles won by 63-223 nats, of which the unobserved term alone gave 84-366 nats:
the flips put more model points on observed surface. Eq. (1) here weighs each point's descriptor,
classifier and unobserved terms by its visibility ``v_i`` in ``[0, 1]``; observed free space is
charged for every point, seen or not (a point in free space contradicts the pose wherever it is).

Visibility of point ``i`` from a camera at ``c`` (object frame) depends, under the object's own
occlusion, only on the direction ``d_i = (c - p_i) / ||c - p_i||`` from the point to the camera.
:class:`VisibilityTable` tabulates it once per object model: for each direction of a cube map
(``faces`` x ``faces`` cells per face, plus a ring of cells past each face's edges so that every
look-up interpolates within one face) a ray is cast from each point towards the camera against
small square splats of all the points (open3d's ``RaycastingScene``). At a pose the kernel looks
up every point's own direction (exact perspective, no orthographic approximation), blends the
table bilinearly (continuous in the pose) and multiplies by a facing ramp
``clip(n_i . d_i / grazing, 0, 1)`` (back faces 0, grazing faces faded in, as depth sensors see
them). With several views of a scene a point counts with its largest visibility.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.validation import check_points

__all__ = ["VisibilityTable", "cached_visibility_table", "cube_directions", "remember_table",
           "scene_cameras", "table_in_memory",
           "visibility_table"]

log = logging.getLogger(__name__)


def cube_directions(faces: int) -> NDArray[np.float64]:
    """Unit directions of the cube map's cells, shape ``(6, faces + 2, faces + 2, 3)``.

    Face ``k`` looks along axis ``k // 2`` with sign ``+`` for even ``k``; cell ``(i, j)``
    (``i, j`` in ``0 .. faces + 1``; 0 and ``faces + 1`` are the ring past the face's edges)
    is centred at face coordinates ``u = (2 i - 1) / faces - 1``, ``v = (2 j - 1) / faces - 1``
    along the face's two other axes in increasing order.
    """
    F = int(faces)
    if F < 1:
        raise ValueError(f"`faces` must be a positive integer, got {faces}.")
    c = (2.0 * np.arange(F + 2) - 1.0) / F - 1.0
    u, v = np.meshgrid(c, c, indexing="ij")
    out = np.empty((6, F + 2, F + 2, 3))
    for k in range(6):
        a = k // 2
        e1, e2 = [x for x in range(3) if x != a]
        d = np.zeros((F + 2, F + 2, 3))
        d[..., a] = 1.0 if k % 2 == 0 else -1.0
        d[..., e1] = u
        d[..., e2] = v
        out[k] = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return out


def _splats(points: NDArray[np.float64], normals: NDArray[np.float64],
            half: float) -> tuple[NDArray[np.float32], NDArray[np.uint32]]:
    """Two triangles per point: a square of side ``2 half`` in its tangent plane."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    corners = np.stack([points + half * (s1 * t1 + s2 * t2)
                        for s1, s2 in ((-1, -1), (1, -1), (1, 1), (-1, 1))], axis=1)
    V = corners.reshape(-1, 3).astype(np.float32)
    base = 4 * np.arange(points.shape[0], dtype=np.uint32)[:, None]
    T = np.concatenate([base + np.array([0, 1, 2], dtype=np.uint32),
                        base + np.array([0, 2, 3], dtype=np.uint32)])
    return V, T


@dataclass(frozen=True)
class VisibilityTable:
    """Self-occlusion of an object model's points by direction of view (see the module).

    Attributes
    ----------
    table : (N, 6 (faces + 2)**2) ndarray of uint8, or None
        1 where point ``i``'s ray towards the cell's direction leaves the object unobstructed
        (rows in the model's point order; cells as :func:`cube_directions` flattened). None for
        a convex surface, which hides nothing from a point that faces the camera.
    normals : (N, 3) ndarray
        The points' outward unit normals.
    faces : int
        Cells per cube face side.
    grazing : float
        ``n . d`` at which the facing ramp reaches 1 (in ``(0, 1]``).
    """

    table: NDArray[np.uint8] | None
    normals: NDArray[np.float64]
    faces: int
    grazing: float

    def visibility(self, points: ArrayLike, camera: ArrayLike) -> NDArray[np.float64]:
        """Visibility ``v_i`` in ``[0, 1]`` of the model points ``points`` (N, 3) (object frame,
        the model's own, in its order) from a camera centre ``camera`` (3,) in the object frame.
        The numpy form of what the eq. (1) kernel computes."""
        p = check_points(points, "points", min_points=1)
        if p.shape[0] != self.normals.shape[0]:
            raise ValueError(f"Expected `points` to have {self.normals.shape[0]} rows, got {p.shape[0]}.")
        c = np.asarray(camera, dtype=np.float64).reshape(3)
        d = c - p
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        facing = np.clip(np.einsum("ij,ij->i", d, self.normals) / self.grazing, 0.0, 1.0)
        if self.table is None:
            return facing
        F = self.faces
        a = np.argmax(np.abs(d), axis=1)
        rows = np.arange(p.shape[0])
        da = d[rows, a]
        k = 2 * a + (da < 0)
        e1 = np.where(a == 0, 1, 0)
        e2 = np.where(a == 2, 1, 2)
        u = d[rows, e1] / np.abs(da)
        v = d[rows, e2] / np.abs(da)
        gx = (u + 1.0) * 0.5 * F + 0.5
        gy = (v + 1.0) * 0.5 * F + 0.5
        i0 = np.clip(np.floor(gx).astype(np.int64), 0, F)
        j0 = np.clip(np.floor(gy).astype(np.int64), 0, F)
        fx, fy = gx - i0, gy - j0
        S = F + 2
        base = k * S * S
        t = self.table
        occ = ((1 - fx) * (1 - fy) * t[rows, base + i0 * S + j0]
               + fx * (1 - fy) * t[rows, base + (i0 + 1) * S + j0]
               + (1 - fx) * fy * t[rows, base + i0 * S + j0 + 1]
               + fx * fy * t[rows, base + (i0 + 1) * S + j0 + 1])
        return facing * occ


def visibility_table(points: ArrayLike, normals: ArrayLike, *, spacing: float | None = None,
                     faces: int = 16, grazing: float = 0.25) -> VisibilityTable:
    """Tabulate the self-occlusion of an object's surface points (see the module docstring).

    Parameters
    ----------
    points : (N, 3) array_like
        Surface points in the object frame, metres (an :class:`~certpose.geometry.objects.
        ObjectModel`'s ``points``).
    normals : (N, 3) array_like
        Their outward normals.
    spacing : float, optional
        Metres: the points' typical distance to their nearest neighbours (None: measured, the
        median distance to the 4th nearest). Splats are squares of side ``1.5 spacing`` (they
        overlap: no holes), rays start ``spacing / 2`` off the surface along the normal.
    faces : int, optional
        Cube-map cells per face side (16: cells about 5.6 degrees wide).
    grazing : float, optional
        ``n . d`` where the facing ramp reaches 1 (0.25: faces seen within about 14 degrees of
        edge-on count partly).

    Returns
    -------
    VisibilityTable
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    p = check_points(points, "points", min_points=4)
    n = np.asarray(normals, dtype=np.float64)
    if n.shape != p.shape or not np.all(np.isfinite(n)):
        raise ValueError(f"Expected finite `normals` of shape {p.shape}, got {n.shape}.")
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    if np.any(norm < 1e-9):
        raise ValueError("`normals` has zero rows: every point needs a direction.")
    n = n / norm
    if not (0 < grazing <= 1):
        raise ValueError(f"`grazing` must be in (0, 1], got {grazing}.")
    if spacing is None:
        spacing = float(np.median(cKDTree(p).query(p, k=min(5, p.shape[0]))[0][:, -1]))
    if not (math.isfinite(spacing) and spacing > 0):
        raise ValueError(f"`spacing` must be positive and finite, got {spacing}.")
    dirs = cube_directions(faces).reshape(-1, 3)
    # Rays only where the point can face the cell's direction: the facing ramp zeroes the rest,
    # and a bilinear blend reaches at most one cell (under 0.2 in n . d) past the horizon.
    if _convex(p, spacing):
        # A convex surface hides nothing from a point it faces: no table.
        return VisibilityTable(None, n, int(faces), float(grazing))
    cand = (n.astype(np.float32) @ dirs.T.astype(np.float32)) > -0.2
    table = np.zeros((p.shape[0], dirs.shape[0]), dtype=np.uint8)
    V, T = _splats(p, n, 0.75 * spacing)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(T))
    origins = (p + 0.5 * spacing * n).astype(np.float32)
    ii, ss = np.nonzero(cand)
    hidden = np.empty(ii.size, dtype=bool)
    # Chunks bound the rays' memory.
    for s in range(0, ii.size, 2_000_000):
        sl = slice(s, s + 2_000_000)
        rays = np.concatenate([origins[ii[sl]], dirs[ss[sl]].astype(np.float32)], axis=1)
        hidden[sl] = scene.test_occlusions(o3d.core.Tensor(np.ascontiguousarray(rays))).numpy()
    table[ii, ss] = ~hidden
    log.debug("visibility table: %d points x %d directions, %.1f%% open", p.shape[0], dirs.shape[0],
              100.0 * table.mean())
    return VisibilityTable(table, n, int(faces), float(grazing))


def _convex(p: NDArray[np.float64], spacing: float) -> bool:
    """Whether every point lies on the points' convex hull (within half a spacing)."""
    import open3d as o3d
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(p)
    except QhullError:  # flat: a plane hides nothing from the side it faces
        return True
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(p.astype(np.float32)),
                        o3d.core.Tensor(hull.simplices.astype(np.uint32)))
    d = scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()
    return bool(np.all(d <= 0.5 * spacing))


_TABLES: dict[bytes, VisibilityTable] = {}
_TABLES_MAX = 16


def _table_key(points: ArrayLike, normals: ArrayLike, grazing: float) -> bytes:
    import hashlib

    p = np.ascontiguousarray(points, dtype=np.float64)
    n = np.ascontiguousarray(normals, dtype=np.float64)
    return hashlib.sha1(p.tobytes() + n.tobytes() + repr((p.shape, float(grazing))).encode()).digest()


def remember_table(points: ArrayLike, normals: ArrayLike, table: VisibilityTable, *,
                   grazing: float = 0.25) -> None:
    """Keep ``table`` as :func:`cached_visibility_table`'s table of these points and normals
    (a table read back from disk, :func:`certpose.io.cache.visibility_table_cached`)."""
    if len(_TABLES) >= _TABLES_MAX:
        _TABLES.pop(next(iter(_TABLES)))
    _TABLES[_table_key(points, normals, grazing)] = table


def table_in_memory(points: ArrayLike, normals: ArrayLike, *, grazing: float = 0.25) -> bool:
    """Whether :func:`cached_visibility_table` holds the table of these points and normals."""
    return _table_key(points, normals, grazing) in _TABLES


def cached_visibility_table(points: ArrayLike, normals: ArrayLike, *, grazing: float = 0.25) -> VisibilityTable:
    """:func:`visibility_table` with default options, kept in memory for the same points and
    normals (a process builds the likelihood of one model many times: each frame, each
    sampler), and on disk when the program turned that on
    (:func:`~certpose.io.derived.use_derived_cache`). At most ``_TABLES_MAX`` tables are kept in
    memory."""
    p = np.ascontiguousarray(points, dtype=np.float64)
    n = np.ascontiguousarray(normals, dtype=np.float64)
    table = _TABLES.get(_table_key(p, n, grazing))
    if table is None:
        table = _from_disk(p, n, float(grazing))
        remember_table(p, n, table, grazing=grazing)
    return table


def _from_disk(points: NDArray[np.float64], normals: NDArray[np.float64], grazing: float,
               built: VisibilityTable | None = None) -> VisibilityTable:
    """:func:`visibility_table` through the derived-data cache (:mod:`certpose.io.derived`);
    ``built``: the table, already built (stored when the cache lacks it)."""
    from certpose.io.derived import cached_arrays

    def compute() -> dict[str, NDArray[Any]]:
        t = built if built is not None else visibility_table(points, normals, grazing=grazing)
        out = {"normals": t.normals, "faces": np.array(t.faces), "grazing": np.array(t.grazing)}
        if t.table is not None:
            out["table"] = t.table
        return out

    inputs = points.tobytes() + normals.tobytes() + repr((points.shape, grazing)).encode()
    d = cached_arrays("visibility", inputs, (__name__,), compute)
    return VisibilityTable(d.get("table"), np.asarray(d["normals"], dtype=np.float64), int(d["faces"]),
                           float(d["grazing"]))


def scene_cameras(scene: Any) -> NDArray[np.float64]:
    """Camera centres (K, 3) of the views a scene keeps (scene frame); (0, 3) when none."""
    frames = tuple(getattr(scene, "frames", ()) or ())
    if not frames:
        return np.zeros((0, 3))
    return np.ascontiguousarray([np.asarray(f.T_world_camera, dtype=np.float64)[:3, 3] for f in frames])
