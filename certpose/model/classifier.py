"""The object classifier ``p_O``: log-probability that a scene voxel belongs to the object.

Two classifiers, both returning an :class:`ObjectClassification` on the scene's voxel grid:

* :func:`classify_best_buddies`, the appendix's: best-buddy similarity between object and
  scene descriptors, thresholded into a noisy binary output; negatives get ``c_min``.
* :func:`classify_from_mask`: from a segmentation mask of a frame (e.g. YCB-Video's
  ``label.png``): an occupied voxel is positive when its centre projects into the mask at a
  pixel whose depth agrees with it.

Only occupied voxels are classified; every other voxel holds ``c_min`` (eq. (1) handles empty
and unobserved space itself, see :mod:`certpose.model.likelihood`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from certpose.model.grid import OCCUPIED, scene_grid_spec

if TYPE_CHECKING:
    from certpose.geometry.objects import ObjectModel
    from certpose.geometry.rgbd import RGBDFrame

__all__ = [
    "ClassifierParams",
    "ClassifierStatus",
    "ObjectClassification",
    "classify_best_buddies",
    "classify_from_mask",
]

log = logging.getLogger(__name__)

class ClassifierStatus(str, Enum):
    """Outcome of a classification."""

    OK = "ok"
    """At least one occupied voxel is classified as the object."""
    NO_POSITIVES = "no_positives"
    """No voxel is classified as the object: a pose estimate has nothing to go on."""

    @property
    def success(self) -> bool:
        return self is ClassifierStatus.OK


@dataclass(frozen=True)
class ClassifierParams:
    """Output values of the binary classifiers.

    Attributes
    ----------
    log_p_positive : float
        ``log p_O`` of a positive voxel (<= 0); default ``log 0.9``.
    c_min : float
        ``log p_O`` of a negative voxel: a large negative value instead of ``-inf``.
    """

    log_p_positive: float = math.log(0.9)
    c_min: float = -5.0

    def __post_init__(self) -> None:
        for name in ("log_p_positive", "c_min"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise ValueError(f"`{name}` must be finite, got {v}.")
            object.__setattr__(self, name, v)
        if self.log_p_positive > 0:
            raise ValueError(f"`log_p_positive` must be <= 0, got {self.log_p_positive}.")
        if not self.c_min < self.log_p_positive:
            raise ValueError(
                f"`c_min` ({self.c_min}) must be below `log_p_positive` ({self.log_p_positive})."
            )


@dataclass(frozen=True, eq=False)
class ObjectClassification:
    """``log p_O`` on a scene's voxel grid.

    Attributes
    ----------
    log_p : (X, Y, Z) ndarray of float64
        Log-probability that each voxel belongs to the object; meaningful at occupied voxels,
        ``c_min`` elsewhere.
    positive : (X, Y, Z) ndarray of bool
        Occupied voxels classified as the object.
    c_min : float
        The value given to negatives.
    method : str
        ``"best_buddies"`` or ``"mask"``.
    status : ClassifierStatus
    message : str
    """

    log_p: NDArray[np.float64]
    positive: NDArray[np.bool_]
    c_min: float
    method: str
    status: ClassifierStatus
    message: str

    @property
    def success(self) -> bool:
        return self.status.success

    @property
    def num_positive(self) -> int:
        return int(np.count_nonzero(self.positive))


def _finish(scene: Any, positive: NDArray[np.bool_], params: ClassifierParams, method: str,
            detail: str) -> ObjectClassification:
    log_p = np.full(positive.shape, params.c_min)
    log_p[positive] = params.log_p_positive
    n_pos = int(positive.sum())
    n_occ = int(np.count_nonzero(np.asarray(scene.state) == OCCUPIED))
    if n_pos == 0:
        status, msg = ClassifierStatus.NO_POSITIVES, f"no occupied voxel classified as the object ({detail})"
    else:
        status, msg = ClassifierStatus.OK, f"{n_pos}/{n_occ} occupied voxels positive ({detail})"
    log.info("classifier %s: %s", method, msg)
    for arr in (log_p, positive):
        arr.setflags(write=False)
    return ObjectClassification(log_p, positive, params.c_min, method, status, msg)


def _occupied(scene: Any) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    state = np.asarray(scene.state)
    idx = np.argwhere(state == OCCUPIED)
    if idx.shape[0] == 0:
        raise ValueError("The scene has no occupied voxel; nothing to classify.")
    return idx, scene_grid_spec(scene).centres(idx)


def _nearest_both_ways(
    a: NDArray[np.float32], b: NDArray[np.float32], k: int, chunk: int = 2048
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float32]]:
    """Top-``k`` of ``b`` for each row of ``a``, the best row of ``a`` for each row of ``b``
    (by inner product) and that best similarity."""
    na, nb = a.shape[0], b.shape[0]
    k = min(k, nb)
    top_b = np.empty((na, k), dtype=np.int64)
    best_a = np.zeros(nb, dtype=np.int64)
    best_a_sim = np.full(nb, -np.inf, dtype=np.float32)
    for s in range(0, na, chunk):
        sim = a[s:s + chunk] @ b.T
        top_b[s:s + chunk] = np.argpartition(-sim, k - 1, axis=1)[:, :k]
        arg = np.argmax(sim, axis=0)
        val = sim[arg, np.arange(nb)]
        better = val > best_a_sim
        best_a[better] = arg[better] + s
        best_a_sim[better] = val[better]
    return top_b, best_a, best_a_sim


def classify_best_buddies(
    scene: Any,
    object_model: ObjectModel,
    *,
    scene_neighbors: int = 10,
    min_similarity: float = 0.0,
    params: ClassifierParams | None = None,
) -> ObjectClassification:
    """Best-buddy classifier (the paper's appendix, after Dekel et al. 2015).

    An occupied scene voxel ``j`` and an object point ``i`` are best buddies when ``i`` is the
    object point most similar to ``j`` and ``j`` is among the ``scene_neighbors`` scene voxels
    most similar to ``i`` (inner products of descriptors; with ``scene_neighbors=1`` this is the
    strict mutual-nearest-neighbour rule, which can mark at most N voxels). A voxel is positive
    when it has a best buddy with similarity ``>= min_similarity``: a noisy binary output whose
    negatives get ``c_min``.

    Parameters
    ----------
    scene : SceneField
    object_model : ObjectModel
    scene_neighbors : int, optional
        ``k`` of the relaxed rule (>= 1).
    min_similarity : float, optional
        Threshold on the best buddy's inner product, in ``[-1, 1]``.
    params : ClassifierParams, optional

    Returns
    -------
    ObjectClassification

    Raises
    ------
    ValueError
        Mismatched descriptor dimensions, NaN descriptors, or a scene without occupied voxels.
    """
    params = params or ClassifierParams()
    if int(scene_neighbors) < 1:
        raise ValueError(f"`scene_neighbors` must be >= 1, got {scene_neighbors}.")
    if not -1.0 <= float(min_similarity) <= 1.0:
        raise ValueError(f"`min_similarity` must be in [-1, 1], got {min_similarity}.")
    idx, _ = _occupied(scene)
    desc = np.asarray(scene.descriptors)
    d = desc.shape[-1]
    if object_model.dim != d:
        raise ValueError(f"Descriptor dimensions differ: object {object_model.dim}, scene {d}.")
    s = desc[idx[:, 0], idx[:, 1], idx[:, 2]].astype(np.float32)
    if not np.all(np.isfinite(s)):
        raise ValueError("`scene.descriptors` contains NaN or inf values at occupied voxels.")
    z = object_model.descriptors.astype(np.float32)
    top_scene, best_obj, best_sim = _nearest_both_ways(z, s, int(scene_neighbors))
    # j is a buddy when its best object point i lists j among its top-k scene voxels.
    mutual = (top_scene[best_obj] == np.arange(s.shape[0])[:, None]).any(axis=1)
    hit = mutual & (best_sim >= min_similarity)
    positive = np.zeros(np.asarray(scene.state).shape, dtype=bool)
    positive[tuple(idx[hit].T)] = True
    detail = f"best buddies, k={int(scene_neighbors)}, min similarity {float(min_similarity):g}"
    return _finish(scene, positive, params, "best_buddies", detail)


def classify_from_mask(
    scene: Any,
    frame: RGBDFrame,
    mask: ArrayLike | None = None,
    *,
    depth_tolerance: float | None = None,
    params: ClassifierParams | None = None,
) -> ObjectClassification:
    """Mask-based classifier: occupied voxels whose centre is seen inside a segmentation mask.

    Each occupied voxel centre is projected into ``frame``; it is positive when it lands on a
    mask pixel whose measured depth is within ``depth_tolerance`` of the centre's depth (so
    background voxels just outside the silhouette, seen past its edge, stay negative).

    Parameters
    ----------
    scene : SceneField
        In the world frame of ``frame.T_world_camera``.
    frame : RGBDFrame
    mask : (H, W) array_like of bool, optional
        The object's pixels; default ``frame.mask``.
    depth_tolerance : float, optional
        Metres; default twice the scene's voxel size.
    params : ClassifierParams, optional

    Returns
    -------
    ObjectClassification

    Raises
    ------
    ValueError
        Missing or empty mask, mask of the wrong shape, a scene without occupied voxels.
    """
    from certpose.geometry.rgbd import check_mask

    params = params or ClassifierParams()
    if mask is None:
        mask = frame.mask
    if mask is None:
        raise ValueError("No `mask` given and `frame.mask` is None.")
    m = check_mask(mask, "mask", frame.shape)
    vs = scene_grid_spec(scene).voxel_size
    tol = 2.0 * vs if depth_tolerance is None else float(depth_tolerance)
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(f"`depth_tolerance` must be positive, got {depth_tolerance}.")
    idx, centres = _occupied(scene)
    T = frame.T_camera_world
    pc = centres @ T[:3, :3].T + T[:3, 3]
    u, v, z = frame.intrinsics.project(pc)
    ok = np.isfinite(u) & np.isfinite(v)
    col = np.full(u.shape, -1, dtype=np.int64)
    row = np.full(v.shape, -1, dtype=np.int64)
    col[ok] = np.floor(u[ok] + 0.5).astype(np.int64)
    row[ok] = np.floor(v[ok] + 0.5).astype(np.int64)
    h, w = frame.shape
    ok &= (col >= 0) & (col < w) & (row >= 0) & (row < h)
    hit = np.zeros(u.shape, dtype=bool)
    r, c = row[ok], col[ok]
    depth = frame.depth[r, c]
    hit[ok] = m[r, c] & (depth > 0) & (np.abs(depth - z[ok]) <= tol)
    positive = np.zeros(np.asarray(scene.state).shape, dtype=bool)
    positive[tuple(idx[hit].T)] = True
    return _finish(scene, positive, params, "mask", f"mask of {int(m.sum())} pixels")
