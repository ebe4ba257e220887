"""Surfaces of revolution in object models: find the axis, and sample them with its symmetry.

Why. Eq. (1) sums per-point terms over the model's surface samples; turning a model about an
axis of revolution of its surface (a mug's body, a can, a bowl) leaves the surface where it was,
so eq. (1) should not change, but an irregular (Poisson-disk) sampling of that surface moves its
samples to other places in the scene's grid and the sum drifts by several nats along the turn
(on YCB-Video 0000's mug, inside the hidden-handle arc, the body's share varies by 14-18 nats
with the default likelihood, most of eq. (1)'s range there; ``examples/benchmarks/bench_arc.py``). A
sampling that is itself invariant under turns of ``2 pi / K`` about the axis (one wedge of the
samples, turned ``K`` times) is a periodic quadrature in the angle: for a field that is smooth
at the spacing of its ``K`` nodes per ring its sum hardly depends on the turn, at the same
number of points.

What. :func:`find_revolution_axis` looks for an axis about which a share of the input points'
turns stay on the input's surface (an axis of the principal directions, its position and
direction refined by Nelder-Mead on the turned points' truncated distance to the input, then
to the input's tangent planes); :func:`revolution_part` marks the samples whose turns stay on
it; :func:`wedge_resample` replaces those by ``K`` turns of one wedge of them (without holes,
holding the mean count). Samples off the surface of revolution (a mug's handle) are kept as they
are. :func:`certpose.geometry.objects.object_from_points` ``revolution="auto"`` does all three
(an option, off by default). On YCB-Video's models (``points.xyz``, tolerance 2.5 times their
median spacing) an axis holds 0.87-0.88 of the cans' points, 0.93 of the mug's, 0.81 of the
large marker's and all of the bowl's; the boxes, the mustard bottle, the banana, the drill and
the wood block 0.08-0.40 (none: the least share is 0.6).

Measured (``examples/benchmarks/bench_arc.py --step 5 [--revolution auto]``, frames 1-5, the
computed arc, ratio of eq. (1)'s range inside to its drop outside; a flat arc with a steep drop
would read <= 0.25):

================================================  ==============================  ===============
likelihood                                        without (mean)                  with (mean)
================================================  ==============================  ===============
default                                           1.69 2.63 2.88 1.47 1.16 (1.97)  0.30 0.92 0.83
                                                                                  0.60 0.54 (0.64;
                                                                                  sampling seed 1:
                                                                                  1.06)
``--field-blur 0.0025``                           0.81 1.22 1.73 1.13 0.99 (1.18)  0.26 0.78 0.69
                                                                                  0.79 0.37 (0.57)
``--free-space-at point --field-blur 0.0075``     0.30 0.81 0.37 0.61 0.55 (0.53)  **0.13** 0.49
``--tolerance 0.0035 --ramp 0.0025``                                              **0.14** 0.41
                                                                                  **0.13** (0.26)
================================================  ==============================  ===============

The body's range inside the arc falls from 14-18 to 5-12 nats with the default likelihood and
from 4.5-8 to 1.6-4.5 with the blurred set (an unblurred field has structure at the voxel, 5 mm,
near the spacing of the ``K`` nodes per ring, so the ring quadrature helps it less). What is left
is the handle near the arc's far end (frame 2) and frame 4's small drop. The turned copies moved
onto the input's tangent planes (exact geometry, the angles kept) bring most of the drift back
(default likelihood: the body's range 11-21 nats, mean ratio 1.04; the set: 0.30): at eq. (1)'s
sharpness the mug's departure from a circle (0.1-2 mm, ``points.xyz``) is itself what moves it,
and the option's gain is to model the body as round.

Why it is not the default (measured with it as the default of ``object_from_points``): on the 60
YCB-Video pairs (``../shared/tools/ycbv_eval.py``, geometry-only) ADD-S <= 1 cm stays 60/60, but
only the objects with an axis change, and not for the better: the mug's rotation on 0000 frames
2-5 moves from 4-10 deg to 18-156 deg (with its body flat, the handle's other hiding places, e.g.
145..166 deg, tie with the true arc), ADD-S on the 17 pairs of those objects moves by -0.04 to
+0.11 cm (+0.03 or more on 10: one wedge's profile stands for the whole body, which is round
only to 0.1-2 mm; largest ADD-S of all pairs 0.66 cm), non-symmetric rotation
<= 10 deg 21 -> 18 of 46, flips 18 -> 21. The importance sampler (``examples/benchmarks/bench_samplers.py
--seeds 0``): mass over every free run of the arc (``cov U``) 0.90-0.98 (without 0.78-0.90),
in them 0.90-0.95 (0.87-0.93), in the true arc 0.60-0.66 (0.67-0.74), the axis within 5 deg and
1 cm 0.78-0.91 (0.79-0.93).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from solvers.validation import check_points, resolve_rng

__all__ = ["RevolutionAxis", "find_revolution_axis", "revolution_part", "wedge_resample"]

log = logging.getLogger(__name__)

#: Turns (degrees) at which a point of a surface of revolution must still lie on the surface.
TEST_TURNS = (45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0)


@dataclass(frozen=True)
class RevolutionAxis:
    """An axis of revolution of (part of) an object's surface, in the object frame.

    Attributes
    ----------
    point : (3,) ndarray
        A point on the axis, metres (the foot of the input points' centroid on it).
    direction : (3,) ndarray
        Unit direction of the axis.
    fraction : float
        Share of the input points with at least :data:`MIN_TURNS` of their turns
        (:data:`TEST_TURNS`) within the tolerance of the input.
    """

    point: NDArray[np.float64]
    direction: NDArray[np.float64]
    fraction: float

    def rotation(self, angle: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(R, t)`` of the turn by ``angle`` (radians) about the axis: ``x -> R x + t``."""
        R = Rotation.from_rotvec(self.direction * float(angle)).as_matrix()
        return R, self.point - R @ self.point


def _turn(points: NDArray[np.float64], point: NDArray[np.float64], direction: NDArray[np.float64],
          angle: float) -> NDArray[np.float64]:
    # Rodrigues' formula for the unit `direction` (scipy's Rotation costs more than the turn).
    k = direction
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    R = np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)
    return (points - point) @ R.T + point


def _axis_from(x: NDArray[np.float64], base: NDArray[np.float64], frame: NDArray[np.float64],
               scale: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    # x = (2 offsets of the axis point in the plane normal to the direction, 2 tilts).
    d = frame[0] + x[2] * frame[1] + x[3] * frame[2]
    d /= np.linalg.norm(d)
    return base + scale * (x[0] * frame[1] + x[1] * frame[2]), d


def _turns_on_surface(points: NDArray[np.float64], tree: cKDTree, point: NDArray[np.float64],
                      direction: NDArray[np.float64], tolerance: float) -> NDArray[np.int64]:
    """How many of each point's turns (:data:`TEST_TURNS`) lie within ``tolerance`` of the input."""
    count = np.zeros(points.shape[0], dtype=np.int64)
    for a in TEST_TURNS:
        d, _ = tree.query(_turn(points, point, direction, math.radians(a)), distance_upper_bound=tolerance)
        count += d <= tolerance
    return count


#: A point is on the surface of revolution when at least this many of its turns are: a point of
#: a mug's body at the height of the handle's roots has one turn in the hole the handle leaves.
MIN_TURNS = 6


def find_revolution_axis(
    points: ArrayLike,
    *,
    tolerance: float,
    min_fraction: float = 0.6,
    max_points: int = 600,
    search_points: int = 500,
    rng: np.random.Generator | int | None = 0,
) -> RevolutionAxis | None:
    """The axis of revolution of the largest part of the surface that ``points`` sample, if any.

    Each principal direction of the points through their centroid starts a Nelder-Mead search
    (axis position in the normal plane and two tilts) that minimises the mean over points and
    turns (:data:`TEST_TURNS`) of the turned point's distance to the input, truncated at twice
    ``tolerance``; the best axis is kept when at least ``min_fraction`` of the points have
    :data:`MIN_TURNS` of their turns within ``tolerance`` of the input.

    Parameters
    ----------
    points : (N, 3) array_like
        Model points, metres; dense enough that a turned point of the surface lies within
        ``tolerance`` of one of them (YCB-Video's ``points.xyz``: 1-2 mm apart).
    tolerance : float
        Metres (> 0).
    min_fraction : float, optional
        Least share of the points on the surface of revolution (in ``(0, 1]``).
    max_points : int, optional
        The refinement runs on at most this many of the points (a random subset).
    search_points : int, optional
        The search from the principal directions runs on at most this many (a random subset;
        it only has to place the axis within the refinement's reach).
    rng : numpy.random.Generator or int or None, optional
        Draws that subset.

    Returns
    -------
    RevolutionAxis or None
        None when no axis holds ``min_fraction`` of the points.
    """
    pts = check_points(points, "points", min_points=10)
    tol = float(tolerance)
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(f"Expected `tolerance` to be positive and finite, got {tolerance}.")
    if not 0 < min_fraction <= 1:
        raise ValueError(f"Expected `min_fraction` in (0, 1], got {min_fraction}.")
    tree = cKDTree(pts)
    gen = resolve_rng(rng)
    if int(search_points) < 10 or int(max_points) < 10:
        raise ValueError(f"Expected `search_points` and `max_points` >= 10, got {search_points}, {max_points}.")
    sub = pts if pts.shape[0] <= search_points else pts[gen.choice(pts.shape[0], int(search_points), replace=False)]
    centre = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centre, full_matrices=False)
    scale = float(np.ptp(pts, axis=0).max())
    cap = 2 * tol
    best = None
    for k in range(3):
        frame = np.roll(vt, -k, axis=0)

        def cost(x: NDArray[np.float64], frame: NDArray[np.float64] = frame) -> float:
            p, d = _axis_from(x, centre, frame, scale)
            total = 0.0
            for a in TEST_TURNS[1::2]:  # 90, 180, 270 deg: enough to place the axis
                dist, _ = tree.query(_turn(sub, p, d, math.radians(a)), distance_upper_bound=cap)
                total += float(np.minimum(dist, cap).mean())
            return total

        simplex = np.zeros((5, 4))
        simplex[1:, :] = np.diag([0.1, 0.1, 0.1, 0.1])
        # Only a start for the refinement below: a coarse tolerance will do.
        res = minimize(cost, np.zeros(4), method="Nelder-Mead",
                       options={"initial_simplex": simplex, "xatol": 1e-3, "fatol": 1e-6, "maxiter": 400})
        p, d = _axis_from(res.x, centre, frame, scale)
        fraction = float(np.mean(_turns_on_surface(sub, tree, p, d, tol) >= MIN_TURNS))
        log.debug("principal direction %d: fraction %.3f on the surface of revolution", k, fraction)
        if best is None or fraction > best.fraction:
            foot = p + np.dot(centre - p, d) * d
            best = RevolutionAxis(foot, d, fraction)
    if best is None or best.fraction < min_fraction:
        log.info("no axis of revolution (best holds %.2f of the points)", 0.0 if best is None else best.fraction)
        return None
    best = _refine(pts, tree, best, tol, gen, max_points)
    log.info("axis of revolution through %s along %s holds %.2f of the points",
             np.round(best.point, 4), np.round(best.direction, 3), best.fraction)
    return best


def _refine(pts: NDArray[np.float64], tree: cKDTree, axis: RevolutionAxis, tol: float,
            gen: np.random.Generator, max_points: int) -> RevolutionAxis:
    """The axis refined on the points of its surface: turned points' distances to the input's
    tangent planes (normals from 10 neighbours), which, unlike the distance to the nearest input
    point (flat within the points' spacing), place the axis to a fraction of a millimetre."""
    _, nb = tree.query(pts, k=10)
    nbh = pts[nb] - pts[nb].mean(axis=1, keepdims=True)
    normals = np.linalg.svd(nbh, full_matrices=False)[2][:, -1, :]
    on = _turns_on_surface(pts, tree, axis.point, axis.direction, tol) >= MIN_TURNS
    idx = np.flatnonzero(on)
    if idx.size > max_points:
        idx = gen.choice(idx, max_points, replace=False)
    sub = pts[idx]
    d0 = axis.direction
    e1 = np.cross(d0, [1.0, 0.0, 0.0] if abs(d0[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    frame = np.stack([d0, e1, np.cross(d0, e1)])
    scale = float(np.ptp(pts, axis=0).max())

    def cost(x: NDArray[np.float64]) -> float:
        p, d = _axis_from(x, axis.point, frame, scale)
        total = 0.0
        for a in TEST_TURNS:
            q = _turn(sub, p, d, math.radians(a))
            _, j = tree.query(q)
            # Huber-like: a turn into a hole (a handle's root) does not pull the axis.
            total += float(np.minimum(np.abs(np.einsum("ij,ij->i", q - pts[j], normals[j])), tol).mean())
        return total

    simplex = np.zeros((5, 4))
    simplex[1:, :] = np.diag([0.01, 0.01, 0.01, 0.01])
    res = minimize(cost, np.zeros(4), method="Nelder-Mead",
                   options={"initial_simplex": simplex, "xatol": 1e-5, "fatol": 1e-9, "maxiter": 400})
    p, d = _axis_from(res.x, axis.point, frame, scale)
    centre = pts.mean(axis=0)
    foot = p + np.dot(centre - p, d) * d
    fraction = float(np.mean(_turns_on_surface(pts, tree, foot, d, tol) >= MIN_TURNS))
    return RevolutionAxis(foot, d, fraction)


def revolution_part(samples: ArrayLike, points: ArrayLike, axis: RevolutionAxis, *,
                    tolerance: float) -> NDArray[np.bool_]:
    """Which ``samples`` lie on the surface of revolution: at least :data:`MIN_TURNS` of their
    turns (:data:`TEST_TURNS`) within ``tolerance`` (metres) of ``points`` (the input the samples
    were drawn from)."""
    s = check_points(samples, "samples")
    p = check_points(points, "points")
    return _turns_on_surface(s, cKDTree(p), axis.point, axis.direction, float(tolerance)) >= MIN_TURNS


def wedge_resample(
    samples: ArrayLike,
    normals: ArrayLike,
    areas: ArrayLike,
    part: ArrayLike,
    axis: RevolutionAxis,
    *,
    wedges: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Replace the samples on the surface of revolution (``part``) by ``wedges`` turns of one
    wedge of them (angle ``2 pi / wedges`` about ``axis``): a wedge without holes whose count
    of samples is the part's mean per wedge, their areas scaled so that the part's total area is
    kept.

    Parameters
    ----------
    samples, normals : (N, 3) array_like
        Surface samples (metres) and their unit normals.
    areas : (N,) array_like
        The area each sample stands for (m^2).
    part : (N,) array_like of bool
        The samples on the surface of revolution (:func:`revolution_part`).
    axis : RevolutionAxis
    wedges : int
        Number of turns (>= 2).

    Returns
    -------
    samples, normals, areas : ndarrays
        The samples off the part first (unchanged), then the turned wedges.
    """
    s = check_points(samples, "samples")
    n = check_points(normals, "normals")
    a = np.asarray(areas, dtype=np.float64)
    m = np.asarray(part, dtype=bool)
    if n.shape != s.shape or a.shape != (s.shape[0],) or m.shape != (s.shape[0],):
        raise ValueError(f"Expected `normals` {s.shape}, `areas` and `part` ({s.shape[0]},); got "
                         f"{n.shape}, {a.shape}, {m.shape}.")
    if int(wedges) != wedges or wedges < 2:
        raise ValueError(f"Expected `wedges` to be an integer >= 2, got {wedges}.")
    K = int(wedges)
    if m.sum() < K:
        return s, n, a
    d = axis.direction
    # Angle of each part sample about the axis, from a reference direction normal to it.
    e1 = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    rel = s[m] - axis.point
    theta = np.mod(np.arctan2(rel @ e2, rel @ e1), 2 * np.pi)
    width = 2 * np.pi / K
    # The wedge start (on a grid of 1/8 wedge): among the wedges holding at least the median
    # area (no hole, e.g. where a handle covers the body, is copied around), the one whose
    # sample count is nearest the part's mean per wedge (the copies keep the number of points).
    starts = np.arange(0.0, 2 * np.pi, width / 8)
    inside = [np.mod(theta - t0, 2 * np.pi) < width for t0 in starts]
    held = np.array([a[m][w].sum() for w in inside])
    count = np.array([w.sum() for w in inside], dtype=float)
    score = np.where(held >= np.median(held), np.abs(count - m.sum() / K), np.inf)
    sel = inside[int(np.argmin(score))]
    ws, wn, wa = s[m][sel], n[m][sel], a[m][sel]
    wa = wa * a[m].sum() / (K * wa.sum())
    out_s, out_n, out_a = [s[~m]], [n[~m]], [a[~m]]
    for k in range(K):
        R, t = axis.rotation(k * width)
        out_s.append(ws @ R.T + t)
        out_n.append(wn @ R.T)
        out_a.append(wa)
    log.info("surface of revolution: %d samples -> %d (%d turns of %d)", m.sum(), K * sel.sum(), K, sel.sum())
    return np.concatenate(out_s), np.concatenate(out_n), np.concatenate(out_a)
