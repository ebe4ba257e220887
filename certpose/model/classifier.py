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
    "box_mask",
    "check_box",
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
    """Output values of the binary classifiers, and the best-buddy classifier's settings.

    Attributes
    ----------
    log_p_positive : float
        ``log p_O`` of a positive voxel (<= 0); default ``log 0.9``.
    c_min : float
        ``log p_O`` of a negative voxel: a large negative value instead of ``-inf``.
    scene_neighbors : int
        ``k`` of the relaxed best-buddy rule (:func:`classify_best_buddies`).
    min_similarity : float
        Best buddies with a lower inner product are not positives, in ``[-1, 1]``.
    box_margin : float
        With a 2-D box: pixels added on every side of the box before it selects candidate
        voxels (a detector's box may cut the object's edge).
    log_p_box : float or None
        With a 2-D box: ``log p_O`` of occupied voxels inside the box that are not best buddies
        (``None``: ``c_min``). Default ``log 0.5``: about half of a box's surface is the object
        (measured 0.48-0.62 on YCB-Video), and best buddies find only part of it (precision
        0.2-0.98, 20-360 voxels of 800-2000). With ``c_min`` there, the object's unmatched
        surface costs more than unobserved space (``log 0.1``) and the search ends with the
        object hidden (measured on three pairs of frame 000001: ADD-S 2.3, 5.7 and 0.7 cm, against
        0.3, 1.8 and 0.2 cm with ``log 0.5``). ``examples/benchmarks/bench_box.py`` on the 18 pairs of frame
        000001, geometry-only models: ADD-S <= 1 cm in 13/18 with ``log 0.5``, 10/18 with
        ``log 0.3``, 11/18 with ``log 0.7``, and 11/18 with the whole box at ``log 0.9`` (the
        buddies ignored); the 18 cross-scene pairs with appearance models: 15/18 against 13/18
        with the buddies ignored. ``scene_neighbors=30`` gave 11/18; ``min_similarity`` up to
        0.7 removes almost no buddy (their inner products are higher).
    """

    log_p_positive: float = math.log(0.9)
    c_min: float = -5.0
    scene_neighbors: int = 10
    min_similarity: float = 0.0
    box_margin: float = 0.0
    log_p_box: float | None = math.log(0.5)

    def __post_init__(self) -> None:
        for name in ("log_p_positive", "c_min", "min_similarity", "box_margin"):
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
        if int(self.scene_neighbors) != self.scene_neighbors or self.scene_neighbors < 1:
            raise ValueError(f"`scene_neighbors` must be an integer >= 1, got {self.scene_neighbors}.")
        object.__setattr__(self, "scene_neighbors", int(self.scene_neighbors))
        if not -1.0 <= self.min_similarity <= 1.0:
            raise ValueError(f"`min_similarity` must be in [-1, 1], got {self.min_similarity}.")
        if self.box_margin < 0:
            raise ValueError(f"`box_margin` must be >= 0, got {self.box_margin}.")
        if self.log_p_box is not None:
            v = float(self.log_p_box)
            if not (math.isfinite(v) and self.c_min <= v <= self.log_p_positive):
                raise ValueError(f"`log_p_box` must lie in [c_min, log_p_positive] = "
                                 f"[{self.c_min}, {self.log_p_positive}], got {self.log_p_box}.")
            object.__setattr__(self, "log_p_box", v)


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
            detail: str, *, background: NDArray[np.float64] | None = None) -> ObjectClassification:
    """``log p_O``: ``log_p_positive`` at positives, ``background`` (default ``c_min``) elsewhere."""
    log_p = np.full(positive.shape, params.c_min) if background is None else background
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


def check_box(box: Any, shape: tuple[int, int], name: str = "box") -> tuple[float, float, float, float]:
    """Validate a 2-D box ``(x0, y0, x1, y1)`` (pixels; x = column, y = row) against an image
    of ``shape`` ``(H, W)``; return it as floats.

    Raises
    ------
    ValueError
        Not four finite numbers, ``x1 <= x0`` or ``y1 <= y0`` (wrong order or empty), or a box
        that does not overlap the image.
    """
    try:
        b = np.asarray(box, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"Expected `{name}` to be four numbers (x0, y0, x1, y1), got {box!r}.") from exc
    if b.shape != (4,):
        raise ValueError(f"Expected `{name}` to have shape (4,) as (x0, y0, x1, y1), got {b.shape}.")
    if not np.all(np.isfinite(b)):
        raise ValueError(f"`{name}` must be finite, got {b.tolist()}.")
    x0, y0, x1, y1 = (float(x) for x in b)
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"`{name}` must have x1 > x0 and y1 > y0 (x0, y0, x1, y1 in pixels), "
                         f"got ({x0:g}, {y0:g}, {x1:g}, {y1:g}).")
    h, w = shape
    if x1 <= -0.5 or y1 <= -0.5 or x0 >= w - 0.5 or y0 >= h - 0.5:
        raise ValueError(f"`{name}` ({x0:g}, {y0:g}, {x1:g}, {y1:g}) lies outside the "
                         f"{w}x{h} image.")
    return x0, y0, x1, y1


def box_mask(box: Any, shape: tuple[int, int], *, margin: float = 0.0) -> NDArray[np.bool_]:
    """The pixels of a 2-D box ``(x0, y0, x1, y1)`` grown by ``margin`` pixels, shape ``(H, W)``.

    A pixel belongs to the box when its centre (integer coordinates) lies inside it.
    """
    x0, y0, x1, y1 = check_box(box, shape)
    if not (math.isfinite(margin) and margin >= 0):
        raise ValueError(f"`margin` must be >= 0, got {margin}.")
    h, w = shape
    rows = np.arange(h, dtype=np.float64)
    cols = np.arange(w, dtype=np.float64)
    in_r = (rows >= y0 - margin) & (rows <= y1 + margin)
    in_c = (cols >= x0 - margin) & (cols <= x1 + margin)
    return in_r[:, None] & in_c[None, :]


def classify_best_buddies(
    scene: Any,
    object_model: ObjectModel,
    *,
    scene_neighbors: int | None = None,
    min_similarity: float | None = None,
    params: ClassifierParams | None = None,
    frame: RGBDFrame | None = None,
    box: Any = None,
) -> ObjectClassification:
    """Best-buddy classifier (the paper's appendix, after Dekel et al. 2015), optionally inside
    a 2-D box.

    An occupied scene voxel ``j`` and an object point ``i`` are best buddies when ``i`` is the
    object point most similar to ``j`` and ``j`` is among the ``scene_neighbors`` scene voxels
    most similar to ``i`` (inner products of descriptors; with ``scene_neighbors=1`` this is the
    strict mutual-nearest-neighbour rule, which can mark at most N voxels). A voxel is positive
    when it has a best buddy with similarity ``>= min_similarity``: a noisy binary output whose
    negatives get ``c_min``.

    With a ``box`` (a detector's output), only occupied voxels whose centre projects into the
    box (grown by ``params.box_margin`` pixels) in ``frame`` are candidates: best buddies are
    sought among them only, and every voxel projecting outside the box is background
    (``c_min``). Candidates that are not positives get ``params.log_p_box``.

    Parameters
    ----------
    scene : SceneField
    object_model : ObjectModel
    scene_neighbors : int, optional
        ``k`` of the relaxed rule (>= 1); default ``params.scene_neighbors``.
    min_similarity : float, optional
        Threshold on the best buddy's inner product, in ``[-1, 1]``; default
        ``params.min_similarity``.
    params : ClassifierParams, optional
    frame : RGBDFrame, optional
        The camera of ``box`` (its intrinsics, image size and ``T_camera_world``); needed with it.
    box : (4,) array_like, optional
        ``(x0, y0, x1, y1)`` in pixels (x = column, y = row), as in YCB-Video's ``box.txt``.

    Returns
    -------
    ObjectClassification

    Raises
    ------
    ValueError
        Mismatched descriptor dimensions, NaN descriptors, a scene without occupied voxels, a
        ``box`` without ``frame``, a malformed box (not four numbers, wrong order, empty,
        outside the image), or a box that holds no occupied voxel.
    """
    params = params or ClassifierParams()
    k = params.scene_neighbors if scene_neighbors is None else scene_neighbors
    thr = params.min_similarity if min_similarity is None else min_similarity
    if int(k) != k or int(k) < 1:
        raise ValueError(f"`scene_neighbors` must be >= 1, got {scene_neighbors}.")
    if not -1.0 <= float(thr) <= 1.0:
        raise ValueError(f"`min_similarity` must be in [-1, 1], got {min_similarity}.")
    k = int(k)
    idx, centres = _occupied(scene)
    candidate = np.ones(idx.shape[0], dtype=bool)
    if box is not None:
        if frame is None:
            raise ValueError("A `box` needs the `frame` it was drawn in.")
        inside = box_mask(box, frame.shape, margin=params.box_margin)
        row, col, _, ok = frame.pixels_of(centres)
        candidate = ok.copy()
        candidate[ok] = inside[row[ok], col[ok]]
        if not candidate.any():
            raise ValueError(f"No occupied voxel of the scene projects into the box "
                             f"{tuple(round(float(x), 2) for x in box)}: is it the box of this frame?")
    desc = np.asarray(scene.descriptors)
    d = desc.shape[-1]
    if object_model.dim != d:
        raise ValueError(f"Descriptor dimensions differ: object {object_model.dim}, scene {d}.")
    cand = idx[candidate]
    s = desc[cand[:, 0], cand[:, 1], cand[:, 2]].astype(np.float32)
    if not np.all(np.isfinite(s)):
        raise ValueError("`scene.descriptors` contains NaN or inf values at occupied voxels.")
    z = object_model.descriptors.astype(np.float32)
    top_scene, best_obj, best_sim = _nearest_both_ways(z, s, k)
    # j is a buddy when its best object point i lists j among its top-k scene voxels.
    mutual = (top_scene[best_obj] == np.arange(s.shape[0])[:, None]).any(axis=1)
    hit = mutual & (best_sim >= thr)
    positive = np.zeros(np.asarray(scene.state).shape, dtype=bool)
    positive[tuple(cand[hit].T)] = True
    detail = f"best buddies, k={k}, min similarity {float(thr):g}"
    background = None
    if box is not None:
        detail += f", {cand.shape[0]} occupied voxels in the box"
        if params.log_p_box is not None:
            background = np.full(positive.shape, params.c_min)
            background[tuple(cand.T)] = params.log_p_box
    return _finish(scene, positive, params, "best_buddies", detail, background=background)


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
    row, col, z, ok = frame.pixels_of(centres)
    hit = np.zeros(z.shape, dtype=bool)
    r, c = row[ok], col[ok]
    depth = frame.depth[r, c]
    hit[ok] = m[r, c] & (depth > 0) & (np.abs(depth - z[ok]) <= tol)
    positive = np.zeros(np.asarray(scene.state).shape, dtype=bool)
    positive[tuple(idx[hit].T)] = True
    return _finish(scene, positive, params, "mask", f"mask of {int(m.sum())} pixels")
