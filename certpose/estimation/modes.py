r"""Competing modes of eq. (1): the object's near-symmetries, tried from the winning pose.

The coarse search samples rotations at random and keeps a few distinct hypotheses; a basin
that it ranks low is never refined (measured on YCB-Video: a box or a can returned flipped by
180 degrees while eq. (1) prefers the unflipped pose by up to 350 nats). Near-symmetries of the
shape are where such basins sit, and they are known in advance: the 24 rotations that map the
object's principal axes onto themselves (about its centroid), which contain the 180-degree
flips of boxes and cans and the 90-degree turns of square sections.

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
    from certpose.model.likelihood import PoseLikelihood

__all__ = ["PoseMode", "principal_symmetries", "explore_modes"]

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

    Returns
    -------
    list of PoseMode
        Best first; the winner itself is among them (origin ``"mle"``), possibly not first.
    """
    from certpose.estimation.batch import refine_poses

    T0 = check_transform(T_scene_object, "T_scene_object", atol=1e-3)
    coarse = coarse_likelihood or likelihood
    scale = object_model.radius
    turns = T0 @ principal_symmetries(object_model.points)
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
    pre = [(0.0, k, T_pre[k]) for k in range(len(turns))]
    exact = np.asarray(likelihood(T_pre))
    order = np.argsort(-exact)[: int(num_refine)]
    modes = [PoseMode(T0, float(likelihood(T0)), "mle")]
    T_fine, v_fine = refine_poses(likelihood, T_pre[order], scale=scale, max_iter=maxiter,
                                  max_step=0.1, prune_margin=prune_margin)
    for j, i in enumerate(order):
        modes.append(PoseMode(T_fine[j], float(v_fine[j]), f"turn:{pre[i][1]}"))
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
