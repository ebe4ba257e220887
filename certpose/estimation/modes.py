r"""Competing modes of eq. (1): the object's near-symmetries, tried from the winning pose.

The coarse search samples rotations at random and keeps a few distinct hypotheses; a basin
that it ranks low is never refined (measured on YCB-Video: a box or a can returned flipped by
180 degrees while eq. (1) prefers the unflipped pose by up to 350 nats). Near-symmetries of the
shape are where such basins sit, and they are known in advance: the 24 rotations that map the
object's principal axes onto themselves (about its centroid), which contain the 180-degree
flips of boxes and cans and the 90-degree turns of square sections.

An object with an axis of revolution (a can, a bowl, a mug's body) has a continuous ambiguity
instead: any turn about the axis fits its shape, and no local maximum stands out on the ring.
:func:`revolution_turns` lists that ring on a grid (and the ring turned upside down), and
:func:`explore_modes` reports the grid's poses that score within ``ring_margin`` of the best
after a short climb: the ring as a set of modes, so that a pose within half a grid step of any
pose on it is among them. Measured on the shared YCB-Video scenes (geometry-only models, mask
classifier): without the ring, the 46 non-symmetric pairs had a reported mode within 10 deg of
the truth in 35; all 11 misses were cans and mugs (tuna fish and tomato soup cans, the mug with
its handle hidden) and one banana at 11.9 deg.

:func:`explore_modes` applies each of them to the winning pose, ranks them on eq. (1), refines
the promising ones, and returns every local maximum found (deduplicated) as a
:class:`PoseMode`. Modes within a few nats of the best are what a user must be told about: a
box's flips without appearance, say.
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.validation import check_transform

if TYPE_CHECKING:
    from certpose.geometry.objects import ObjectModel
    from certpose.geometry.revolution import RevolutionAxis
    from certpose.model.likelihood import PoseLikelihood

__all__ = ["PoseMode", "explore_modes", "principal_symmetries", "revolution_axis", "revolution_turns"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class PoseMode:
    """A local maximum of eq. (1).

    Attributes
    ----------
    T_scene_object : (4, 4) ndarray
    log_likelihood : float
        Eq. (1) at the pose, nats.
    origin : str
        How it was found: ``"mle"`` (the search's winner) or ``"turn:<k>"`` (the winner turned by
        the ``k``-th principal-axis rotation, then refined).
    rotation_from_best_deg : float
        Rotation angle between this mode and the best one, degrees.
    """

    T_scene_object: NDArray[np.float64]
    log_likelihood: float
    origin: str
    rotation_from_best_deg: float = 0.0

    def to_dict(self) -> dict[str, object]:
        return {"T_scene_object": self.T_scene_object.tolist(),
                "log_likelihood": float(self.log_likelihood), "origin": self.origin,
                "rotation_from_best_deg": float(self.rotation_from_best_deg)}


def principal_symmetries(points: ArrayLike) -> NDArray[np.float64]:
    """The 23 non-identity rotations that permute the principal axes of ``points``, about their centroid.

    Parameters
    ----------
    points : (N, 3) array_like
        Object frame, metres.

    Returns
    -------
    (23, 4, 4) ndarray
        Object-frame transforms ``S``; a pose ``T`` turned by ``S`` is ``T @ S``.
    """
    p = np.asarray(points, dtype=np.float64)
    c = p.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((p - c).T))
    if np.linalg.det(vecs) < 0:
        vecs[:, 0] *= -1.0
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            M = np.zeros((3, 3))
            M[np.arange(3), list(perm)] = signs
            if np.linalg.det(M) < 0 or np.allclose(M, np.eye(3)):
                continue
            R = vecs @ M @ vecs.T
            S = np.eye(4)
            S[:3, :3] = R
            S[:3, 3] = c - R @ c
            out.append(S)
    return np.stack(out)


#: Least share of an object's points that must lie on its surface of revolution for
#: :func:`revolution_axis` to return the axis.
RING_MIN_FRACTION = 0.6

#: Tolerance of :func:`revolution_axis`'s test, in median neighbour gaps of the points. On
#: YCB-Video's object models as ``certpose pose --ycbv`` samples them (gap about 3 mm) one gap
#: gives the tomato soup and tuna fish cans, the bowl, the mug and the large marker (and the
#: demo's mug) 0.87-1.00 of their points and every other object 0.06-0.47. At 2.5 gaps (7.4 mm)
#: the gelatin box, the foam brick, the banana and the wood block passed as bodies of revolution
#: too (0.56-0.88 of their points), and :func:`explore_modes` listed a ring of turns for them.
AXIS_TOLERANCE_GAPS = 1.0

#: Tolerance, in median neighbour gaps, of the search that places an axis that passed the test:
#: wider, so that all of a can's points weigh in (1.00 of them against 0.92 at one gap). The two
#: axes differ by up to 0.07 deg and 0.06 mm on YCB-Video's mug and cans, enough to move a ring
#: pose across the edge of the modes' window: with the axis placed at one gap the tomato soup can
#: in 0050/000001 lost its one mode within 10 deg of the truth (107 nats below the best, the
#: window's edge).
AXIS_FIT_GAPS = 2.5

_AXES: dict[bytes, RevolutionAxis | None] = {}


def revolution_axis(points: ArrayLike) -> RevolutionAxis | None:
    """The points' axis of revolution, or None.

    :func:`~certpose.geometry.revolution.find_revolution_axis` at tolerance
    :data:`AXIS_TOLERANCE_GAPS` median neighbour gaps of the points decides whether at least
    :data:`RING_MIN_FRACTION` of them lie on a surface of revolution; the axis returned is then
    placed by the same search at :data:`AXIS_FIT_GAPS` gaps. Both the ring of
    :func:`explore_modes` and the model-error kernel's tilt/spin split
    (``PoseParams.model_error_tilt``) use it. Kept per distinct point set in memory, and on disk
    when the program turned that on (:mod:`certpose.io.derived`; each search takes 0.2-1 s).

    Parameters
    ----------
    points : (N, 3) array_like
        Object model points (object frame, metres), evenly spaced as an object model's voxel
        samples are: one median gap is a strict tolerance for scattered samples (a cylinder
        sampled at random holds 0.06 of its points at one gap, 0.92 at two; YCB-Video's raw
        ``points.xyz`` show no axis at one gap).

    Returns
    -------
    RevolutionAxis or None
        ``fraction`` is the share of the points on the surface at :data:`AXIS_TOLERANCE_GAPS`.
    """
    import hashlib

    from scipy.spatial import cKDTree

    from certpose.geometry.revolution import RevolutionAxis, find_revolution_axis
    from certpose.io.derived import cached_arrays

    pts = np.ascontiguousarray(points, dtype=np.float64)
    key = hashlib.sha1(pts.tobytes()).digest()
    if key not in _AXES:

        def compute() -> dict[str, NDArray[np.float64]]:
            gap = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1]))
            if not gap > 0:
                return {"none": np.zeros(0)}
            def search(gaps: float) -> RevolutionAxis | None:
                return find_revolution_axis(pts, tolerance=gaps * gap, min_fraction=RING_MIN_FRACTION,
                                            max_points=400, search_points=250)

            test = search(AXIS_TOLERANCE_GAPS)
            if test is None:
                return {"none": np.zeros(0)}
            fit = search(AXIS_FIT_GAPS) or test
            return {"point": fit.point, "direction": fit.direction, "fraction": np.array(test.fraction)}

        inputs = pts.tobytes() + repr((pts.shape, RING_MIN_FRACTION, AXIS_TOLERANCE_GAPS, AXIS_FIT_GAPS)).encode()
        d = cached_arrays("revolution-axis", inputs, (__name__, "certpose.geometry.revolution"), compute)
        axis = None if "none" in d else RevolutionAxis(d["point"], d["direction"], float(d["fraction"]))
        if len(_AXES) > 64:
            _AXES.clear()
        _AXES[key] = axis
    return _AXES[key]


def revolution_turns(points: ArrayLike, *, step_deg: float = 15.0) -> tuple[NDArray[np.float64], list[str]]:
    """The turns about the points' axis of revolution, on a grid, upright and upside down.

    Parameters
    ----------
    points : (N, 3) array_like
        Object frame, metres.
    step_deg : float
        Degrees between turns (in (0, 90]; 360 / step rounded to an integer count).

    Returns
    -------
    turns : (K, 4, 4) ndarray
        Object-frame transforms ``S`` (a pose ``T`` turned is ``T @ S``): the turns by
        ``k * step`` (``k >= 1``) about the axis, then every turn composed with the half turn
        about an axis normal to it through the centroid's foot on it. Empty (0, 4, 4) when the
        points have no axis of revolution (:func:`revolution_axis`).
    labels : list of str
        ``"ring:<deg>"`` and ``"ring-flip:<deg>"``.
    """
    p = np.asarray(points, dtype=np.float64)
    if not (math.isfinite(step_deg) and 0 < step_deg <= 90):
        raise ValueError(f"`step_deg` must be in (0, 90] degrees, got {step_deg}.")
    axis = revolution_axis(p)
    if axis is None:
        return np.zeros((0, 4, 4)), []
    from scipy.spatial.transform import Rotation

    d, c = axis.direction, axis.point
    n = int(round(360.0 / step_deg))
    e = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    e /= np.linalg.norm(e)
    flip = np.eye(4)
    flip[:3, :3] = Rotation.from_rotvec(math.pi * e).as_matrix()
    flip[:3, 3] = c - flip[:3, :3] @ c
    out, labels = [], []
    for k in range(n):
        S = np.eye(4)
        S[:3, :3] = Rotation.from_rotvec(2 * math.pi * k / n * d).as_matrix()
        S[:3, 3] = c - S[:3, :3] @ c
        deg = 360.0 * k / n
        if k:
            out.append(S)
            labels.append(f"ring:{deg:g}")
        out.append(S @ flip)
        labels.append(f"ring-flip:{deg:g}")
    return np.stack(out), labels


def _angle_deg(Ra: NDArray[np.float64], Rb: NDArray[np.float64]) -> float:
    cos = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def explore_modes(
    likelihood: PoseLikelihood,
    T_scene_object: ArrayLike,
    object_model: ObjectModel,
    *,
    coarse_likelihood: PoseLikelihood | None = None,
    num_refine: int = 6,
    maxiter: int = 40,
    min_angle_deg: float = 10.0,
    prune_margin: float | None = 50.0,
    ring_margin: float | None = None,
) -> list[PoseMode]:
    """Local maxima of eq. (1) at the near-symmetric turns of a pose (see the module docstring).

    Parameters
    ----------
    likelihood : PoseLikelihood
        The exact eq. (1).
    T_scene_object : (4, 4) array_like
        The search's winner (a local maximum of ``likelihood``).
    object_model : ObjectModel
        The model ``likelihood`` was built with.
    coarse_likelihood : PoseLikelihood, optional
        A cheaper, smoother eq. (1) (e.g. on a subsample, free space eroded) to rank and
        pre-refine the turns; default ``likelihood``.
    num_refine : int
        Turns refined on the exact eq. (1) (the best after pre-refinement).
    maxiter : int
        Iteration limit of each refinement.
    min_angle_deg : float
        Modes closer than this in rotation (and half the object radius in translation) to a
        better one are the same mode.
    prune_margin : float or None
        Turns whose recent climb, carried on to the last iteration, would still leave them
        more than this many nats below the best turn stop (``prune_margin`` of
        :func:`~certpose.estimation.batch.refine_poses`, checked every 10 iterations).
        Replayed on the exact refinements' values of the 60 pairs of
        ``examples/benchmarks/bench_basins.py`` and of the potted-meat can in 0002/000020 with an
        appearance model (whose winning turn climbs from 220 nats behind): it spares half the
        evaluations, and no turn it stops would have ended within 15 nats of the winner. A
        plain cut at a fixed distance behind the best turn (60 nats after 10 iterations) lost
        the potted-meat can's turn. ``None``: every turn runs to the end.
    ring_margin : float or None
        Nats. With an axis of revolution (:func:`revolution_turns`), the ring's grid poses
        whose exact eq. (1) after the coarse climb is within this of the best are returned too
        (origin ``"ring:<deg>"`` or ``"ring-flip:<deg>"``; not refined on the exact eq. (1)).
        ``None``: no ring.

    Returns
    -------
    list of PoseMode
        Best first; the winner itself is among them (origin ``"mle"``), possibly not first.
    """
    from certpose.estimation.batch import refine_poses

    T0 = check_transform(T_scene_object, "T_scene_object", atol=1e-3)
    coarse = coarse_likelihood or likelihood
    scale = object_model.radius
    S = principal_symmetries(object_model.points)
    labels = [f"turn:{k}" for k in range(len(S))]
    if ring_margin is not None:
        R, ring_labels = revolution_turns(object_model.points)
        S, labels = np.concatenate([S, R]), labels + ring_labels
    turns = T0 @ S
    # A turn moves the visible side: try each on a grid of translations (as the coarse search
    # does, 0.15 object radii apart), keep its best on the coarse eq. (1) (measured: the
    # mustard bottle's unflipped turn stalls 150 nats below its peak without this).
    o = np.array([-0.15, 0.0, 0.15]) * scale
    shifts = np.stack(np.meshgrid(o, o, o, indexing="ij"), axis=-1).reshape(-1, 3)
    grid = np.repeat(turns[:, None], shifts.shape[0], axis=1)
    grid[:, :, :3, 3] += shifts[None]
    values = np.asarray(coarse(grid.reshape(-1, 4, 4))).reshape(len(turns), -1)
    turns = grid[np.arange(len(turns)), np.argmax(values, axis=1)]
    # All turns climb together on the coarse eq. (1): one batched call per iteration.
    T_pre, _ = refine_poses(coarse, turns, scale=scale, max_iter=max(5, maxiter // 2))
    exact = np.asarray(likelihood(T_pre))
    ring = np.array([lab.startswith("ring") for lab in labels])
    order = np.argsort(np.where(ring, -np.inf, exact))[::-1][: int(num_refine)]
    modes = [PoseMode(T0, float(likelihood(T0)), "mle")]
    T_fine, v_fine = refine_poses(likelihood, T_pre[order], scale=scale, max_iter=maxiter,
                                  max_step=0.1, prune_margin=prune_margin)
    for j, i in enumerate(order):
        modes.append(PoseMode(T_fine[j], float(v_fine[j]), labels[i]))
    if ring.any():
        top = max(m.log_likelihood for m in modes)
        for i in np.flatnonzero(ring & (exact >= top - float(ring_margin))):
            modes.append(PoseMode(T_pre[i], float(exact[i]), labels[i]))
    modes.sort(key=lambda m: -m.log_likelihood)
    kept: list[PoseMode] = []
    for m in modes:
        same = any(
            _angle_deg(m.T_scene_object[:3, :3], o.T_scene_object[:3, :3]) < min_angle_deg
            and np.linalg.norm(m.T_scene_object[:3, 3] - o.T_scene_object[:3, 3]) < 0.5 * scale
            for o in kept
        )
        if not same:
            kept.append(m)
    best = kept[0].T_scene_object[:3, :3]
    return [PoseMode(m.T_scene_object, m.log_likelihood, m.origin,
                     _angle_deg(best, m.T_scene_object[:3, :3])) for m in kept]
