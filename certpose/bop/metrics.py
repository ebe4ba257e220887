"""Pose errors of the BOP benchmark (VSD, MSSD, MSPD) and the classic ADD / ADD-S.

The definitions are the BOP toolkit's (``bop_toolkit_lib.pose_error``) in certpose's units:
poses ``(R, t)`` map model points into the camera frame with ``t``, points, depth, diameters
and ``delta`` all in metres (the toolkit's millimetres divided by 1000: VSD and MSSD are
normalised by the diameter, MSPD is in pixels, so the scores are unit-free).

* VSD (visible surface discrepancy): the model rendered at both poses, each rendering's
  visible part judged against the test depth image with tolerance ``delta`` (a pixel without
  test depth counts as visible, BOP 2019's rule), and the share of the union of the two
  visible parts where the renderings differ by ``tau`` or more (or only one is visible).
* MSSD / MSPD: the largest 3-D / image distance between the model's vertices at the estimate
  and at the ground truth, minimised over the object's symmetries.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["distance_image", "visible_masks", "vsd", "mssd", "mspd", "add", "adi",
           "spheres_overlap", "sphere_projections_overlap"]


def distance_image(depth: NDArray[np.float64], K: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distance from the camera centre of each pixel's 3-D point (0 where ``depth`` is 0)."""
    h, w = depth.shape
    xs = (np.arange(w, dtype=np.float64) - K[0, 2]) / K[0, 0]
    ys = (np.arange(h, dtype=np.float64) - K[1, 2]) / K[1, 1]
    d = depth.astype(np.float64)
    return np.sqrt((xs[None, :] * d) ** 2 + (ys[:, None] * d) ** 2 + d ** 2)


def _visible(d_test: NDArray[np.float64], d_model: NDArray[np.float64], delta: float
             ) -> NDArray[np.bool_]:
    # The toolkit compares in float32.
    diff = d_model.astype(np.float32) - d_test.astype(np.float32)
    return ((diff <= delta) | (d_test == 0)) & (d_model > 0)


def visible_masks(dist_test: NDArray[np.float64], dist_gt: NDArray[np.float64],
                  dist_est: NDArray[np.float64], delta: float
                  ) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """The visible parts of the ground-truth and the estimated renderings (distance images):
    the estimate's also where the ground truth's is visible and the estimate is rendered."""
    visib_gt = _visible(dist_test, dist_gt, delta)
    visib_est = _visible(dist_test, dist_est, delta) | (visib_gt & (dist_est > 0))
    return visib_gt, visib_est


def vsd(depth_est: NDArray[np.float64], depth_gt: NDArray[np.float64],
        depth_test: NDArray[np.float64], K: NDArray[np.float64], *, delta: float,
        taus: NDArray[np.float64], diameter: float | None) -> NDArray[np.float64]:
    """VSD errors, one per ``tau``, from the two renderings' depth images.

    Parameters
    ----------
    depth_est, depth_gt : (H, W) ndarray
        The model rendered at the estimate and at the ground truth (0: no surface), metres.
    depth_test : (H, W) ndarray
        The test image's depth, metres (0: no measurement).
    K : (3, 3) ndarray
    delta : float
        Visibility tolerance, metres (BOP: 15 mm).
    taus : (T,) array_like
        Misalignment tolerances: fractions of ``diameter`` (or metres when it is None).
    diameter : float or None
        Normalises the distances (BOP 2019: yes).

    Returns
    -------
    ndarray, shape (T,)
        In [0, 1]; 1 when neither rendering is visible.
    """
    dist_test = distance_image(depth_test, K)
    dist_gt = distance_image(depth_gt, K)
    dist_est = distance_image(depth_est, K)
    visib_gt, visib_est = visible_masks(dist_test, dist_gt, dist_est, delta)
    inter = visib_gt & visib_est
    union = int((visib_gt | visib_est).sum())
    taus = np.asarray(taus, dtype=np.float64)
    if union == 0:
        return np.ones(len(taus))
    comp = union - int(inter.sum())
    dists = np.abs(dist_gt[inter] - dist_est[inter])
    if diameter is not None:
        dists = dists / diameter
    return np.array([(np.sum(dists >= tau) + comp) / float(union) for tau in taus])


def _moved(points: NDArray[np.float64], R: NDArray[np.float64], t: NDArray[np.float64]
           ) -> NDArray[np.float64]:
    return points @ np.asarray(R).T + np.asarray(t).reshape(3)


def mssd(R_est: NDArray[np.float64], t_est: NDArray[np.float64], R_gt: NDArray[np.float64],
         t_gt: NDArray[np.float64], points: NDArray[np.float64],
         symmetries: NDArray[np.float64]) -> float:
    """Maximum symmetry-aware surface distance: ``min_S max_x ||T_est x - T_gt S x||``.

    Parameters
    ----------
    points : (N, 3) ndarray
        Model vertices, metres.
    symmetries : (K, 4, 4) ndarray
        Identity first (see :func:`certpose.io.bop.symmetry_transforms`).
    """
    pe = _moved(points, R_est, t_est)
    best = np.inf
    for S in symmetries:
        pg = _moved(points, R_gt @ S[:3, :3], R_gt @ S[:3, 3] + np.reshape(t_gt, 3))
        best = min(best, float(np.linalg.norm(pe - pg, axis=1).max()))
    return best


def _project(points: NDArray[np.float64], K: NDArray[np.float64]) -> NDArray[np.float64]:
    p = points @ K.T
    return p[:, :2] / p[:, 2:3]


def mspd(R_est: NDArray[np.float64], t_est: NDArray[np.float64], R_gt: NDArray[np.float64],
         t_gt: NDArray[np.float64], K: NDArray[np.float64], points: NDArray[np.float64],
         symmetries: NDArray[np.float64]) -> float:
    """Maximum symmetry-aware projection distance, pixels (as :func:`mssd`, in the image)."""
    pe = _project(_moved(points, R_est, t_est), K)
    best = np.inf
    for S in symmetries:
        pg = _project(_moved(points, R_gt @ S[:3, :3], R_gt @ S[:3, 3] + np.reshape(t_gt, 3)), K)
        best = min(best, float(np.linalg.norm(pe - pg, axis=1).max()))
    return best


def add(R_est: NDArray[np.float64], t_est: NDArray[np.float64], R_gt: NDArray[np.float64],
        t_gt: NDArray[np.float64], points: NDArray[np.float64]) -> float:
    """ADD: mean distance between corresponding model points."""
    return float(np.linalg.norm(_moved(points, R_est, t_est) - _moved(points, R_gt, t_gt),
                                axis=1).mean())


def adi(R_est: NDArray[np.float64], t_est: NDArray[np.float64], R_gt: NDArray[np.float64],
        t_gt: NDArray[np.float64], points: NDArray[np.float64]) -> float:
    """ADD-S (ADI): mean distance from each true model point to the nearest estimated one, as
    the BOP toolkit's ``adi``."""
    from scipy.spatial import cKDTree

    return float(cKDTree(_moved(points, R_est, t_est)).query(
        _moved(points, R_gt, t_gt), k=1)[0].mean())


def spheres_overlap(t_est: NDArray[np.float64], t_gt: NDArray[np.float64],
                    diameter: float) -> bool:
    """The toolkit's shortcut for MSSD and ADD: centres closer than the diameter."""
    return bool(np.linalg.norm(np.reshape(t_est, 3) - np.reshape(t_gt, 3)) < diameter)


def sphere_projections_overlap(t_est: NDArray[np.float64], t_gt: NDArray[np.float64],
                               radius: float) -> bool:
    """The toolkit's shortcut for VSD: whether the image discs of the two bounding spheres
    (approximately) overlap."""
    p1, p2 = np.reshape(t_est, 3), np.reshape(t_gt, 3)
    if p1[2] == 0 or p2[2] == 0:
        return False
    dist = np.linalg.norm(p1[:2] / p1[2] - p2[:2] / p2[2])
    return bool(dist < radius * (1.0 / p1[2] + 1.0 / p2[2]))
