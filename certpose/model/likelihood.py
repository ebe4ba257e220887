r"""Eq. (1) of the paper: the log-likelihood of an object pose, for a batch of poses at once.

.. math::

    \log p(\mathcal{O}_{R,t}) = \sum_{i=1}^N \log p_\mathcal{O}(q_i) + \beta f_{scn}(q_i)^T z_i,
    \qquad q_i = R p_i + t .

Object models sampled evenly over their surface carry the area each point stands for
(:attr:`~certpose.geometry.objects.ObjectModel.areas`); their terms are weighted by
``areas[i] / voxel_size**2``, so the sum approximates the same surface integral however densely
the surface is sampled.

How the special scene states enter, voxel by voxel:

* **occupied** voxel ``v``: ``log p_O(v)`` from the classifier and ``beta * f_v^T z_i``;
* **empty** (observed free space, ``z^T z_emp = -inf``): the finite free-space penalty
  ``c_empty`` (a large negative log-probability, as the appendix does for ``c_min``). Optionally
  graded by how deep the voxel lies in free space (``free_space_tolerance``,
  ``free_space_ramp``, ``free_space_from``; :func:`free_space_values`): free space within a
  voxel of its boundary costs what unobserved space costs, deep free space the full penalty.
  By default the first layer of free space next to unobserved space or a surface (5 mm) is
  spared and the penalty ramps up to full at 10 mm: depth sensors leave invalid or mixed
  pixels along silhouettes and on dark parts, and a true pose a few pixels off the image's
  silhouette would otherwise pay ``c_empty`` for hundreds of points. Measured on the 60
  YCB-Video frame-object pairs (geometry-only models, mask classifier; see
  :class:`LikelihoodParams`);
* **unobserved** (behind surfaces, outside the image or outside the grid; ``z^T z_null = 0``):
  similarity 0 and a neutral classifier prior ``log_p_unobserved`` (default ``log 0.1``). It
  sits between a classifier positive (``log 0.9``) and a negative (``c_min = -5``): hidden
  object points pay neither a penalty nor earn the reward of an observed match. It must stay
  well below the positives' value: with ``log 0.5`` the few free-space violations caused by
  depth noise at the true pose outweigh the reward of the visible points, and eq. (1) prefers
  to hide the whole object in unobserved space (measured on YCB-Video, see
  ``examples/benchmarks/bench_ycbv.py``).

At a continuous point the per-voxel terms of the 8 surrounding voxel centres are blended
trilinearly. Because the blend is linear, this equals trilinear interpolation of ``f_scn``
(with ``z_null = 0`` descriptors) plus trilinear interpolation of ``log p_O`` (with the values
above at empty and unobserved voxels), and the objective is continuous in the pose.

**What the camera sees: the change against the paper's eq. (1).** The paper sums over every
object point. By default (``LikelihoodParams.visibility``, with per-pixel free space) the term of
point ``i`` is instead

.. math::

    v_i(R, t) \, [\log p_\mathcal{O}(q_i) + \beta f_{scn}(q_i)^T z_i]
    + (1 - v_i(R, t)) \log p_{unobserved} + \phi_i(R, t),

with ``v_i`` in ``[0, 1]`` the point's visibility from the scene's cameras at the pose (facing
them and not hidden by the object itself, :mod:`certpose.model.visibility`) and ``phi_i`` the
free-space charge of the depth images (:mod:`certpose.model.freespace`), paid by every point,
seen or not. A point the object hides carries no evidence for or against the pose: it costs
what unobserved space costs wherever it lands. Why: on real YCB-Video frames that certpose was
not tuned on, every non-symmetric geometry-only pose came back flipped by 180 degrees, and eq.
(1) at the flip minus eq. (1) at the refined truth was +70 to +223 nats, of which the unobserved
term alone gave +84 to +366: the flips put 8-26% more model points on observed surface, because
the model's sampled surface was lopsided (the cracker box's two large faces 244 and 200 cm^2)
and the back faces voted. With a faithful surface
(:func:`~certpose.geometry.objects.sample_surface`: the convex hull of convex inputs, 328 and
320 cm^2) and visibility, the flips of a box seen from one side score within the scatter of
eq. (1) over sampling seeds (about 1-2% of the visible weight, tests/test_visibility.py), where
the paper's eq. (1) on an unevenly sampled surface prefers the flip that shows the denser face
by about 1,000 nats.

**Surface no view saw: the colour of an unseen point.** A model built from posed views
(:mod:`certpose.geometry.appearance`) knows the colour of the points its views saw; the others
carry a zero colour block, the ``z_null`` of that block. Scored so, a pose earns colour only from
seen points, and on a frame that shows what the views did not see, the turn that brings the seen
side to the camera collects every agreement of the object's common colours. The mustard bottle in
YCB-Video 0050/000020 with a model from scene 0002's views (which saw 2% of what that frame
shows): eq. (1) preferred the turn to the refined truth by 538 nats, 446 of them from the colour
of seen points. Projected into the image at the turn, those points' colours overlap the image's
(soft hue and grey bins) by 0.52 on average, a random colour of the seen palette by 0.44 and the
bottle's front as 0050's own views see it by 0.70: the reward was the palette's, not the
pose's. By default (``LikelihoodParams.unseen_color="marginal"``) an unseen point's colour term
at an occupied voxel ``v`` is the marginal ``log mean_j exp(beta f_v^c . z_j^c)`` over the
model's coloured points ``j`` (``f^c``, ``z^c``: the colour blocks): a pose earns colour only
where the colours it shows match better than one of the object's colours, unknown which, would.
With appearance models that sample the surface
(:func:`~certpose.geometry.appearance.object_from_posed_views`), on the 18 cross-scene pairs of
``examples/benchmarks/bench_box.py --models appearance --classifier mask --seed 0`` (mustard
bottle, potted-meat can, banana; models never built from the scene scored): where the views saw
at least a third of what the frame shows (12 pairs) rotation <= 10 deg in 12 as before; where
they saw less (the 6 mustard pairs, 2-5%) 3 against 0, and the truth inside the sampled
distribution's 90% credible region in 6 against 0 (levels 0.55-0.83 against 1.00). Crediting
unseen points with the largest similarity instead (``"best"``, voxel-averaged models) turned the
cans and bananas, whose flips show unseen surface: rotation <= 10 deg 4 of those 12.
"""

from __future__ import annotations

import functools
import logging
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from certpose.model.grid import EMPTY, OCCUPIED, scene_grid_spec
from solvers.jit import compiled
from solvers.validation import as_float_array

if TYPE_CHECKING:
    from certpose.geometry.objects import ObjectModel
    from certpose.model.classifier import ObjectClassification

__all__ = ["LikelihoodParams", "PoseLikelihood", "palette_similarity", "blurred_descriptors", "blurred_terms", "free_space_depths",
           "free_space_values", "log_likelihood", "resolve_free_space"]

log = logging.getLogger(__name__)

#: Point terms (poses times object points) a thread must get for a batch to be split among the
#: pool's threads: below it, handing a chunk to a thread costs about what it saves. A count of
#: poses alone misjudged both eq. (1)s of the MLE: 16 poses of a 128-point coarse model (2,000
#: terms, a tenth of a millisecond) went to two threads, 8 poses of a 2,300-point model did not.
_PARALLEL_MIN_TERMS = 8192


@functools.lru_cache(maxsize=1)
def _pool() -> tuple[ThreadPoolExecutor, int]:
    """Threads for large batches (the eq. (1) kernel releases the GIL): one per core this
    process may run on, at most numba's thread count (``NUMBA_NUM_THREADS``), so that a
    process told to run numba on one thread (a Dask worker of a one-thread-per-core cluster)
    does not split its batches among threads that only compete with the other workers."""
    from numba import config

    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        n = os.cpu_count() or 1
    n = max(1, min(n, int(config.NUMBA_NUM_THREADS)))
    return ThreadPoolExecutor(max_workers=n, thread_name_prefix="eq1"), n

@dataclass(frozen=True)
class LikelihoodParams:
    """Constants of eq. (1).

    Attributes
    ----------
    beta : float
        Temperature of the visual-similarity term (>= 0; dimensionless).
    c_empty : float
        Log-probability of an object point in observed free space (finite, negative).
    log_p_unobserved : float
        Neutral classifier log-prior of an object point in unobserved space (<= 0).
    free_space_erosion : int
        Empty voxels within this many voxels (chessboard distance) of an occupied voxel are
        treated as unobserved: a coarser eq. (1) that tolerates pose errors of that size
        (used by the coarse search; 0 is the exact model).
    free_space_tolerance : float
        Metres (>= 0, default 5 mm, one voxel at the default voxel size). Observed free space
        within this distance of its boundary (see ``free_space_from``) costs
        ``log_p_unobserved`` instead of ``c_empty``: depth noise, invalid pixels on dark parts
        and mixed pixels along silhouettes do not punish a point next to them.
    free_space_ramp : float
        Metres (>= 0, default 5 mm). Beyond ``free_space_tolerance`` the free-space cost falls
        linearly to ``c_empty`` over this distance (0: a step). See :func:`free_space_values`.
    free_space_from : {"surface", "boundary"}
        What the tolerance's distance is measured from: ``"surface"``, the nearest occupied voxel
        centre (an observed surface); ``"boundary"``, the nearest voxel centre that is not
        observed free space (an observed surface or unobserved space: the edge of a shadow or
        of the grid too), i.e. how deep the voxel lies in free space, the measure of
        :func:`certpose.model.arc.free_space_arc`. Default ``"boundary"``.
    free_space_at : {"voxel", "point"}
        Where the tolerance and the ramp are applied. ``"voxel"`` (default): to each EMPTY
        voxel centre's distance (:func:`free_space_values`), and the ramped values are blended
        trilinearly, so a point is charged as soon as one of its 8 voxel centres is, up to
        about half a voxel before it passes the tolerance itself. ``"point"``: the distances
        (:func:`free_space_depths`) are blended trilinearly and half a voxel subtracted (the
        point's depth into free space, the measure of :func:`certpose.model.arc.free_space_arc`),
        and the point pays ``clip((depth - free_space_tolerance) / free_space_ramp, 0, 1)`` of
        ``c_empty - log_p_unobserved``: the charge starts where the point itself passes the
        tolerance. On the mug's hidden-handle arc (``examples/benchmarks/bench_arc.py``, YCB-Video 0000
        frames 1-5, 2-deg steps, refined) the handle's share inside the arc is then flat
        (range 0.0-0.1 nats; 1.2-1.6 with ``field_blur=0.0075``) where the voxel-centre
        ramp charged its tip 5-15 nats near the arc's ends; unrefined, on 0000/000001, no free
        space is charged anywhere inside the arc (tests/test_free_space_at_point.py). But the
        drop to the best angle 10 deg beyond the free runs falls too (-18..-8 nats; with the
        blur -4..3): the points there stand at most a few millimetres past the tolerance and
        the refinement moves them out; the range-to-drop ratio is not better than the
        voxel-centre default's (bench_arc's docstring). With a tolerance under the arc's
        (3.5 mm, ramp 2.5 mm) and the blur the handle's share varies by 1.6-12 nats and the
        drop is 5-22 nats (2-deg ratio 0.47-1.82); the body's sampling is then most of the range,
        and with four times denser points (``density=8``, four times eq. (1)'s cost) the ratio
        is 0.18-0.91 (mean 0.43, the target 0.25 met on frames 1 and 5; the voxel-centre ramp
        with the same points and blur: 0.32-1.15, mean 0.58, met on none). Not the default; no other free-space
        option applies (``free_space="pixels"`` rejects it). The graded kernels it uses cost
        about 0-15% more per evaluation than the default kernel (mostly in cells near free
        space; interleaved, YCB-Video 0000/000001).
    free_space : {"voxels", "pixels", "auto"}
        Where observed free space is read from (``"auto"``: pixels when the scene keeps its depth
        images and no voxel grading option is set, voxels otherwise; :func:`resolve_free_space`). ``"voxels"`` (default): the scene grid's EMPTY
        voxels, blended trilinearly like the other voxel states (the ``free_space_*`` options
        above grade it). ``"pixels"``: the depth images the scene was built from
        (:mod:`certpose.model.freespace`; the scene must keep them, ``SceneField.frames``). A
        point standing ``g`` metres in front of the measured depth of its nearest pixel is
        charged the fraction ``clip((g - depth_tolerance) / depth_ramp, 0, 1)`` of
        ``c_empty - log_p_unobserved`` on top of its voxel term, in which EMPTY voxels then count
        as unobserved; pixels without depth, points outside the image and points behind the
        surface are not charged. ``free_space_erosion`` then widens the tolerance by that many
        voxels (the coarse search's tolerant eq. (1)); ``free_space_tolerance``,
        ``free_space_ramp`` and ``free_space_from`` apply to voxels only (with pixels they must keep
        their defaults).
    depth_tolerance : float
        Metres (>= 0), ``free_space="pixels"`` only: depth in front of the measured surface that
        is not charged (sensor noise, annotation error). Default 1 cm, the voxel grid's default
        carving margin (``build_scene_field``'s ``free_space_margin``).
    depth_ramp : float
        Metres (>= 0), ``free_space="pixels"`` only: beyond ``depth_tolerance`` the charge rises
        linearly to the full penalty over this distance (0: a step).
    depth_window : int
        Pixels (>= 0), ``free_space="pixels"`` only: half-width of the min-filter over the valid
        depths (0: the nearest pixel), so that the mixed pixels at a silhouette do not count the
        space beside a foreground edge as free.
    field_blur : float
        Metres (>= 0, default 0: off). Standard deviation of a Gaussian that spreads the
        classifier's term of each occupied voxel (relative to unobserved space) over its
        neighbours before the trilinear blend (:func:`blurred_terms`; the free-space values
        and the descriptor similarity are not blurred, see ``descriptor_blur``). The observed
        surface is a shell one voxel thick; with about two model points per voxel face, eq. (1)
        summed over them depends on where they fall between voxel centres, and a local
        refinement finds the shifts where they fall favourably: on the mug's hidden-handle arc
        (``examples/benchmarks/bench_arc.py``, YCB-Video 0000 frames 1-5, 5 deg steps) the round body's
        refined share varied by 21-34 nats; with 7.5 mm (1.5 voxels) by 6.7-9.0, and eq. (1)'s
        ratio of range inside to drop outside fell from 0.87-8.55 (mean 4.27) to 0.41-1.15
        (mean 0.69). The body-only model, frames 1 / 2: 30.9 / 31.9 nats unblurred, 7.6 / 6.8
        with 7.5 mm, 12.4 / 17.1 with four times denser points (``density=8``), 3.4 / 3.5
        with both. Not the default: ``examples/benchmarks/bench_basins.py`` (60 YCB-Video pairs,
        geometry-only models, mask classifier; default -> 5 mm -> 7.5 mm) kept 60/60 returned
        >= refined truth - 1 nat, but ADD-S <= 1 cm 60 -> 59 -> 59 (the wood block 0.65 ->
        1.0 cm, its refined truth 1.1 cm), non-symmetric rotation <= 10 deg 15 -> 14 -> 14 of
        46, flips 20 -> 24 -> 25 (the potted meat can twice, within 2.2 nats of its refined
        truth; the tuna can crossing 150 deg); the mug's rotation error on frames 1-4 9.5 /
        72.6 / 140.9 / 73.2 -> 59.9 / 46.9 / 20.2 / 22.4 deg with 7.5 mm. Eq. (1) takes about
        5-9% longer (more cells need the 8-corner blend). With the Voronoi-area models, the
        arc's option set (7.5 mm with ``free_space_at="point"``, tolerance 3.5 mm, ramp 2.5 mm)
        as the default was measured against the defaults of the time and not adopted: the poses hold (``ycbv_eval.py``, 60 pairs:
        ADD-S <= 1 cm 60 -> 59, the wood block 0.53-0.66 -> 0.91-1.02 cm; non-symmetric
        rotation <= 10 deg 21 -> 21, flips 18 -> 16 (the potted meat can twice less, 0049),
        median rotation error 11.8 -> 15.5 deg (the mug on 0000/000002-4 4-10 -> 20-48 deg,
        inside its flatter arc); ``bench_basins.py`` 60/60; ``bench_box.py`` unchanged) and
        the arc's mean ratio falls from inf (sampling seed 0: 1.35-6.27 on four frames, inf on
        the fifth) to 0.67 / 0.55 / 0.46 over sampling seeds 0 / 1 / 2, but the importance
        sampler loses: ``examples/benchmarks/bench_is_seeds.py`` ESS >= 1000 in 28 of 30 runs (least 439,
        0000/000002, where the defaults give 2475) and the mug's axis within 5 deg / 1 cm of
        the truth's for 0.63-0.71 of the mass instead of about 0.90 (two slow tests of the
        demo's tilt fail); it is the blur that moves the axis (the blur alone 0.70, the point
        ramp alone 0.88-0.89). A whole ``certpose pose`` call per frame took 27-32% longer
        (interleaved with the defaults, ``examples/benchmarks/bench_pose_calls.py``: 27.4 / 27.7 against
        21.6 / 21.0 s a round; one call per pair median 2.24 / 2.29 against 2.12 / 1.90 s).
        With 5 mm instead of 7.5 the ESS holds (30/30, least 1237) and the ratio is 0.70 /
        0.66 / 0.53, but the axis still holds only 0.68-0.74 of the mass, and ``ycbv_eval.py``
        gives rotation <= 10 deg 20 of 46, median rotation error 19.7 deg, ADD-S 60/60 (the
        wood block 0.90-1.00 cm).
    visibility : bool
        Default True: each object point's descriptor and classifier terms are blended with the
        unobserved prior by its visibility ``v`` from the scene's cameras at the pose (facing
        the camera and not hidden by the object itself; :mod:`certpose.model.visibility`):
        ``v term + (1 - v) log_p_unobserved``. A point the camera cannot see costs what
        unobserved space costs, whatever lies where it lands; observed free space is charged for
        every point. Needs per-pixel free space (``free_space`` resolved to ``"pixels"``: the
        scene's views), and the model's normals; otherwise every point counts (the paper's
        eq. (1)).
    visibility_grazing : float
        In ``(0, 1]``, default 0.25: ``n . d`` (unit normal and direction to the camera) at which
        a point counts in full; faces seen closer to edge-on count in proportion.
    unseen_color : {"marginal", "best", "none"}
        The colour part of the similarity of an object point that carries no colour (the colour
        block of its descriptor is zero: no view of the model saw it), for scenes described by a
        backbone with a colour block (``scene.backbone.color_columns``, e.g.
        :class:`~certpose.geometry.appearance.AppearanceBackbone`) and models with some coloured
        points. ``"marginal"`` (default): at an occupied voxel ``v``,
        ``log mean_j exp(beta f_v^c . z_j^c) / beta`` over the model's coloured points ``j``
        (of the model the likelihood was built with; :func:`palette_similarity`), the marginal of
        eq. (1)'s term for a point whose colour is one of the seen ones, unknown which.
        ``"best"``: the largest of those similarities (credits unseen surface with the best match
        the object could show there). ``"none"``: zero, the shape block's similarity alone (the
        paper's ``z_null`` for the colour block). Guessed colour blocks (``object_from_posed_views``'
        ``unseen="prior"`` or ``"palette"``) count as colours. See the module docstring for the
        measured reason.
    descriptor_blur : float
        Metres (>= 0, default 0: off). Standard deviation of a Gaussian that spreads the fused
        scene descriptors ``f_v`` of the occupied voxels over their neighbours before the
        trilinear blend (:func:`blurred_descriptors`): the similarity is linear in ``f``, so
        ``beta (G * f)(v)^T z_i`` is the blurred similarity, and summed across the surface it is
        kept (the Gaussian's weights sum to one) while at the shell itself it falls. The voxels
        within the Gaussian's reach of the surface then carry descriptor rows of their own
        (YCB-Video 0000/000001, whole frame: 14,659 occupied voxels; 3.3 times as many rows at
        3.5 mm, 5.9 times at 7.5 mm; ``d`` float32 and one float64 each). On the mug's
        hidden-handle arc (``examples/benchmarks/bench_arc.py``, frames 1-5, 2-deg steps, refined), with
        the best option set there (``free_space_at="point"``, ``field_blur=0.0075``,
        ``free_space_tolerance=0.0035``, ``free_space_ramp=0.0025``) the descriptor
        similarity carries 19-47% of the body's variance inside the arc (its range 3.2-6.5
        nats), the classifier's term the rest; 3.5 mm brings the similarity's range to 2.1-3.9
        nats, the body's to 6.9-8.3 (was 7.6-10.2) and eq. (1)'s range-to-drop ratio from
        0.63 / 0.90 / 0.69 / 1.82 / 0.47 (mean 0.90) to 0.42 / 0.86 / 0.76 / 1.29 / 0.43 (mean
        0.75); with twice / four times denser points (``density`` 4 / 8) mean 0.54 -> 0.52 and
        0.43 -> 0.37 (target 0.25 met on frames 1 and 5 either way at density 8). Wider blurs
        flatten the similarity more but lower the drop outside the arc, whose refinement
        hides the handle more cheaply when the body's similarity falls off more slowly across
        the surface: 5 mm mean 0.90, 7.5 mm 1.17 (2.5 mm 0.80). Alone (voxel-centre free
        space, no ``field_blur``) it changes nothing that matters: the body's share still varies
        by 22-34 nats, its classifier term's. Not the default. Cost per point term (one
        thread, 0000/000001 whole frame, 2,288 mug points, interleaved, 21 rounds): with the
        option set above +10% near the truth and +11% on wide rotations at 3.5 mm (+8% / +13%
        at 7.5 mm); with the default kernel alone +52% / +51% at 3.5 mm, +75% / +87% at 7.5 mm:
        the cells beside the surface then blend 8 descriptor products instead of their
        free-space or unobserved values.

    Notes
    -----
    The free-space defaults (boundary, 5 mm + 5 mm ramp; before: every EMPTY voxel at
    ``c_empty``) were chosen on the 60 YCB-Video frame-object pairs of scenes 0000, 0002, 0049
    and 0050 (geometry-only models from ``points.xyz``, ground-truth mask classifier, the MLE
    of :func:`certpose.estimation.mle.estimate_mle`, seed 0; run side by side): ADD-S <= 1 cm
    in 50/60 -> 59/60, median ADD-S 0.32 -> 0.28 cm, non-symmetric rotation <= 10 deg 10 -> 14
    of 46. At the true pose of the power drill (0050/000001) 710 of its 4,218 model points
    stood in EMPTY voxels 5-10 mm deep, next to the invalid depth along its silhouette (3,098
    nats); hiding the whole drill in unobserved space scored 2,000 nats better, and the MLE was
    4.3 cm off. The wood block, tuna can, cracker box and the second drill frame failed the
    same way. The cost: protrusions that stand only 5-10 mm in free space are charged less,
    e.g. the hidden-handle mug's turns past its arc (``examples/benchmarks/bench_samplers.py``: mass in
    the arc 0.81-1.00 -> 0.13-0.88 on scene 0000, coverage of the arc 0.76-0.87 ->
    0.09-0.96). ``LikelihoodParams(free_space_tolerance=0, free_space_ramp=0,
    free_space_from="surface")`` is the former model.
    """

    beta: float = 1.0
    c_empty: float = -10.0
    log_p_unobserved: float = math.log(0.1)
    free_space_erosion: int = 0
    free_space_tolerance: float = 0.005
    free_space_ramp: float = 0.005
    free_space_from: str = "boundary"
    free_space_at: str = "voxel"
    free_space: str = "auto"
    depth_tolerance: float = 0.01
    depth_ramp: float = 0.0
    depth_window: int | tuple[int, ...] = (5, 10, 15)
    field_blur: float = 0.0
    descriptor_blur: float = 0.0
    visibility: bool = True
    visibility_grazing: float = 0.25
    unseen_color: str = "marginal"

    def __post_init__(self) -> None:
        for name in ("beta", "c_empty", "log_p_unobserved", "free_space_tolerance",
                     "free_space_ramp", "depth_tolerance", "depth_ramp", "field_blur", "descriptor_blur"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise ValueError(f"`{name}` must be finite, got {v}.")
            object.__setattr__(self, name, v)
        if self.beta < 0:
            raise ValueError(f"`beta` must be >= 0, got {self.beta}.")
        if self.c_empty >= 0:
            raise ValueError(f"`c_empty` must be negative, got {self.c_empty}.")
        if self.log_p_unobserved > 0:
            raise ValueError(f"`log_p_unobserved` must be <= 0, got {self.log_p_unobserved}.")
        for name in ("free_space_tolerance", "free_space_ramp", "depth_tolerance", "depth_ramp",
                     "field_blur", "descriptor_blur"):
            if getattr(self, name) < 0:
                raise ValueError(f"`{name}` must be >= 0 metres, got {getattr(self, name)}.")
        if self.free_space_from not in ("surface", "boundary"):
            raise ValueError(
                f"`free_space_from` must be 'surface' or 'boundary', got {self.free_space_from!r}."
            )
        if self.free_space_at not in ("voxel", "point"):
            raise ValueError(
                f"`free_space_at` must be 'voxel' or 'point', got {self.free_space_at!r}.")
        if self.free_space not in ("voxels", "pixels", "auto"):
            raise ValueError(
                f"`free_space` must be 'voxels', 'pixels' or 'auto', got {self.free_space!r}.")
        if self.free_space == "pixels" and self.voxel_grading_changed:
            raise ValueError(
                "`free_space_tolerance`, `free_space_ramp`, `free_space_from` and `free_space_at` "
                "grade the voxel grid's free space; with free_space='pixels' use `depth_tolerance` "
                "and `depth_ramp`."
            )
        if self.unseen_color not in ("marginal", "best", "none"):
            raise ValueError(f"`unseen_color` must be 'marginal', 'best' or 'none', got "
                             f"{self.unseen_color!r}.")
        if not isinstance(self.visibility, (bool, np.bool_)):
            raise TypeError(f"`visibility` must be a bool, got {type(self.visibility).__name__}.")
        g = float(self.visibility_grazing)
        if not (0.0 < g <= 1.0):
            raise ValueError(f"`visibility_grazing` must be in (0, 1], got {self.visibility_grazing}.")
        object.__setattr__(self, "visibility_grazing", g)
        from certpose.model.freespace import check_windows

        try:
            windows = check_windows(self.depth_window)
        except (TypeError, ValueError):
            raise ValueError("`depth_window` must be a non-negative integer or a non-empty tuple of "
                             f"them (pixels), got {self.depth_window!r}.") from None
        object.__setattr__(self, "depth_window", windows[0] if len(windows) == 1 else windows)
        if int(self.free_space_erosion) != self.free_space_erosion or self.free_space_erosion < 0:
            raise ValueError(
                f"`free_space_erosion` must be a non-negative integer, got {self.free_space_erosion}."
            )

    @property
    def voxel_grading_changed(self) -> bool:
        """Whether an option grading the voxel grid's free space (``free_space_tolerance``,
        ``free_space_ramp``, ``free_space_from``, ``free_space_at``) differs from its default."""
        defaults = {f.name: f.default for f in fields(self)}
        return any(getattr(self, f) != defaults[f]
                   for f in ("free_space_tolerance", "free_space_ramp", "free_space_from", "free_space_at"))

    @property
    def graded_at_point(self) -> bool:
        """Whether eq. (1) applies the free-space ramp at the point (``free_space_at="point"``
        with voxel free space)."""
        return self.free_space_at == "point" and self.free_space == "voxels"


def _morton_order(points: NDArray[np.float64], cell: float) -> NDArray[np.int64]:
    """Permutation sorting ``points`` along a Morton curve of cells of side ``cell``."""
    if points.shape[0] == 0:  # e.g. a scene with no occupied voxel
        return np.zeros(0, dtype=np.int64)
    q = np.floor((points - points.min(axis=0)) / cell).astype(np.uint64)
    q = np.minimum(q, np.uint64(2**21 - 1))
    code = np.zeros(points.shape[0], dtype=np.uint64)
    for axis in range(3):
        # Spread the 21 bits of each coordinate three apart (bit b to bit 3 b + axis).
        x = q[:, axis].copy()
        for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                            (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
            x = (x | (x << np.uint64(shift))) & np.uint64(mask)
        code |= x << np.uint64(axis)
    return np.argsort(code, kind="stable")


def _cell_codes(index: NDArray[np.int32], background: NDArray[np.float64], c_empty: float,
                depth: tuple[NDArray[np.float64], float, float, float] | None = None) -> NDArray[np.int8]:
    """Per cell (between 8 neighbouring voxel centres), see :mod:`certpose.model._kernels`:
    ``UNIFORM_UNOBSERVED`` (8 unobserved corners), ``UNIFORM_EMPTY`` (8 non-occupied corners
    holding ``c_empty``), ``UNIFORM`` (8 non-occupied corners sharing another value) or
    ``MIXED``. ``depth``: ``(depths, start, ramp, c_unobs)`` of ``free_space_at="point"``; a
    cell is then ``UNIFORM`` only if no corner is deeper than ``start`` (no charge), and
    ``UNIFORM_EMPTY`` if every corner is charged in full and holds ``c_unobs``."""
    from certpose.model._kernels import (
        MIXED,
        UNIFORM,
        UNIFORM_EMPTY,
        UNIFORM_UNOBSERVED,
        UNOBSERVED_CODE,
    )

    free = _all_corners(index < 0)
    same = free & _equal_corners(background)
    first = background[:-1, :-1, :-1]
    cells = np.full(free.shape, MIXED, dtype=np.int8)
    if depth is None:
        cells[same] = UNIFORM
        cells[same & (first == c_empty)] = UNIFORM_EMPTY
    else:
        g, start, ramp, c_unobs = depth
        cells[same & _all_corners(g <= start)] = UNIFORM
        full = _all_corners((g > start) if ramp == 0 else (g >= start + ramp))
        cells[same & full & (first == c_unobs)] = UNIFORM_EMPTY
    cells[_all_corners(index == UNOBSERVED_CODE)] = UNIFORM_UNOBSERVED
    return cells


def _all_corners(a: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Per cell of the grid ``a`` (X, Y, Z): whether all 8 corners are true, (X-1, Y-1, Z-1);
    one axis at a time (3 passes over the grid instead of 15)."""
    a = a[:-1] & a[1:]
    a = a[:, :-1] & a[:, 1:]
    return a[:, :, :-1] & a[:, :, 1:]


def _equal_corners(b: NDArray[Any]) -> NDArray[np.bool_]:
    """Per cell of the grid ``b`` (X, Y, Z): whether its 8 corners hold one value (NaN equals
    nothing), (X-1, Y-1, Z-1); one axis at a time: the two halves of a cell along an axis are each
    uniform and hold the same value."""
    same = b[:-1] == b[1:]
    b = b[:-1]
    same = same[:, :-1] & same[:, 1:] & (b[:, :-1] == b[:, 1:])
    b = b[:, :-1]
    return same[:, :, :-1] & same[:, :, 1:] & (b[:, :, :-1] == b[:, :, 1:])


def free_space_values(state: ArrayLike, voxel_size: float, params: LikelihoodParams) -> NDArray[np.float64]:
    """Per-voxel value of eq. (1) at voxels that are not occupied, shape ``state.shape``.

    Unobserved voxels hold ``log_p_unobserved``. An observed-free (EMPTY) voxel whose centre lies
    ``d`` metres from the nearest occupied voxel centre (Euclidean distance transform) holds
    ``log_p_unobserved`` while ``d <= free_space_tolerance``, then falls linearly to ``c_empty``
    over ``free_space_ramp`` metres (a step when the ramp is 0): a point a sensor-noise away from
    an observed surface costs about as much as a hidden one, a point deep in free space the full
    penalty. With both at 0 every EMPTY voxel holds ``c_empty``. With
    ``free_space="pixels"`` EMPTY voxels hold ``log_p_unobserved`` (free space is charged per
    pixel instead).
    ``free_space_erosion`` is applied first (eroded voxels are unobserved). Occupied voxels hold 0
    (unused: eq. (1) reads the classifier and the descriptors there). With
    ``free_space_at="point"`` EMPTY voxels hold ``log_p_unobserved`` too (the charge is applied
    per point from :func:`free_space_depths`).

    Parameters
    ----------
    state : (X, Y, Z) array_like of int
        ``UNOBSERVED`` (0), ``EMPTY`` (1) or ``OCCUPIED`` (2).
    voxel_size : float
        Voxel side, metres.
    params : LikelihoodParams

    Returns
    -------
    ndarray, shape (X, Y, Z)
    """
    state = _check_state(state)
    occupied = state == OCCUPIED
    if params.free_space == "pixels" or params.free_space_at == "point":
        # Free space is charged per pixel or per point (PoseLikelihood).
        return np.where(occupied, 0.0, params.log_p_unobserved)
    empty = _observed_free(state, params)
    out = np.full(state.shape, params.log_p_unobserved, dtype=np.float64)
    out[occupied] = 0.0
    tol, ramp = params.free_space_tolerance, params.free_space_ramp
    if tol == 0 and ramp == 0:
        out[empty] = params.c_empty
    elif empty.any():
        # Only distances up to tol + ramp change the value: beyond, the voxel pays c_empty.
        d = _free_distance(state, empty, float(voxel_size), tol + ramp, params)[empty]
        frac = (d > tol).astype(np.float64) if ramp == 0 else np.clip((d - tol) / ramp, 0.0, 1.0)
        graded = params.log_p_unobserved + frac * (params.c_empty - params.log_p_unobserved)
        # Exactly c_empty deep in free space (the kernel's fast path tests for it).
        out[empty] = np.where(frac >= 1.0, params.c_empty, graded)
    return out


def _check_state(state: ArrayLike) -> NDArray[Any]:
    """``state`` as an array, checked to be a 3-D voxel grid."""
    state = np.asarray(state)
    if state.ndim != 3:
        raise ValueError(f"Expected `state` to have shape (X, Y, Z), got {state.shape}.")
    return state


def _observed_free(state: NDArray[Any], params: LikelihoodParams) -> NDArray[np.bool_]:
    """EMPTY voxels after ``free_space_erosion`` (eroded ones count as unobserved)."""
    empty = state == EMPTY
    if params.free_space_erosion > 0:
        from scipy.ndimage import maximum_filter

        # k dilations by the 3x3x3 cube are one by a (2k+1)-cube: separable, 2-3x faster.
        near = maximum_filter((state == OCCUPIED).view(np.uint8),
                              size=2 * int(params.free_space_erosion) + 1, mode="constant", cval=0)
        empty &= near == 0
    return empty


def _free_distance(state: NDArray[Any], empty: NDArray[np.bool_], voxel_size: float, reach: float,
                   params: LikelihoodParams) -> NDArray[np.float64]:
    """Distance (metres) from each voxel centre to what ``free_space_from`` measures from, exact
    up to ``reach`` and ``inf`` beyond."""
    if params.free_space_from == "boundary":
        # Outside the grid is unobserved, so the grid's faces are a boundary too.
        return _distance_to(~empty, voxel_size, reach, outside=True)
    occupied = state == OCCUPIED
    if occupied.any():
        return _distance_to(occupied, voxel_size, reach, outside=False)
    # No observed surface at all: every free voxel is deep in free space.
    return np.where(empty, np.inf, 0.0)


def free_space_depths(state: ArrayLike, voxel_size: float,
                      params: LikelihoodParams) -> tuple[NDArray[np.float64], float]:
    """Per-voxel distances into free space for ``free_space_at="point"``, and where the charge
    starts.

    Each EMPTY voxel (after ``free_space_erosion``) holds the distance (metres) from its centre
    to the nearest voxel centre that is not EMPTY (``free_space_from="boundary"``) or occupied
    (``"surface"``), other voxels 0. Eq. (1) blends these trilinearly at a point: the blend minus
    half a voxel is the point's depth into free space (as in
    :func:`certpose.model.arc.free_space_arc`), and the point pays
    ``clip((depth - free_space_tolerance) / free_space_ramp, 0, 1)`` of
    ``c_empty - log_p_unobserved`` (a step when the ramp is 0). With ``"boundary"`` distances
    beyond ``start + ramp + sqrt(3) voxels`` are stored as that value: the distances of a cell's 8
    corners differ by at most ``sqrt(3)`` voxels (every non-EMPTY corner is a boundary, at 0), so a
    cell with a corner beyond it is charged in full either way. With ``"surface"`` (unobserved
    corners hold 0 but need not be near the surface) they are exact; without any occupied voxel
    every EMPTY voxel holds the grid's diagonal.

    Parameters
    ----------
    state : (X, Y, Z) array_like of int
        ``UNOBSERVED`` (0), ``EMPTY`` (1) or ``OCCUPIED`` (2).
    voxel_size : float
        Voxel side, metres.
    params : LikelihoodParams

    Returns
    -------
    depth : ndarray, shape (X, Y, Z)
        Metres.
    start : float
        Metres, ``free_space_tolerance + voxel_size / 2``: the blended distance beyond which a
        point is charged.
    """
    state = _check_state(state)
    vs = float(voxel_size)
    start = params.free_space_tolerance + 0.5 * vs
    cap = start + params.free_space_ramp + math.sqrt(3.0) * vs
    empty = _observed_free(state, params)
    out = np.zeros(state.shape)
    if not empty.any():
        return out, start
    if params.free_space_from == "boundary":
        out[empty] = np.minimum(_free_distance(state, empty, vs, cap, params)[empty], cap)
    else:
        d = _free_distance(state, empty, vs, math.inf, params)[empty]
        out[empty] = np.where(np.isfinite(d), d, vs * math.sqrt(sum(n * n for n in state.shape)))
    return out, start


def _distance_to(target: NDArray[np.bool_], voxel_size: float, reach: float, *,
                 outside: bool) -> NDArray[np.float64]:
    """Distance (metres) from each voxel centre to the nearest ``target`` voxel centre (0 on
    them), exact up to ``reach`` and ``inf`` beyond; ``outside``: whether the space around the
    grid counts as target.

    Within three voxels this tests the offsets nearest first: 6x faster than scipy's full
    Euclidean distance transform on a YCB-Video grid (4.5 against 28 ms per likelihood) and
    equal to it value for value where the offsets of one length give one value (the same
    arithmetic; the default reach, two voxels), within rounding otherwise. Farther reaches use
    the transform."""
    R = int(min(np.floor(reach / voxel_size + 1e-9), 4.0))
    if R > 3:  # hundreds of offsets: the transform is cheaper
        from scipy.ndimage import distance_transform_edt

        if outside:
            return distance_transform_edt(np.pad(~target, 1), sampling=voxel_size)[1:-1, 1:-1, 1:-1]
        if not target.any():
            return np.full(target.shape, np.inf)
        return distance_transform_edt(~target, sampling=voxel_size)
    shape = target.shape
    padded = np.pad(target, R, constant_values=outside)
    by_norm: dict[int, list[tuple[int, int, int]]] = {}
    for dx in range(-R, R + 1):
        for dy in range(-R, R + 1):
            for dz in range(-R, R + 1):
                k = dx * dx + dy * dy + dz * dz
                if k and math.sqrt(k) * voxel_size <= reach * (1 + 1e-12):
                    by_norm.setdefault(k, []).append((dx, dy, dz))
    d = np.where(target, 0.0, np.inf)
    todo = ~target
    for k in sorted(by_norm):
        for dx, dy, dz in by_norm[k]:
            hit = padded[R + dx:R + dx + shape[0], R + dy:R + dy + shape[1],
                         R + dz:R + dz + shape[2]] & todo
            c = np.array([dx, dy, dz], dtype=np.float64) * voxel_size
            c *= c
            d[hit] = np.sqrt(np.add.reduce(c))  # scipy's order: sum over the axes, then root
            todo &= ~hit
    return d


def blurred_terms(
    index: NDArray[np.int32],
    background: NDArray[np.float64],
    logp: NDArray[np.float64],
    voxel_size: float,
    params: LikelihoodParams,
) -> tuple[NDArray[np.int32], NDArray[np.float64], NDArray[np.float64]]:
    """Eq. (1)'s per-voxel terms with the classifier's spread by ``params.field_blur``.

    The classifier's term relative to unobserved space, ``logp - log_p_unobserved`` at occupied
    voxels and 0 elsewhere, is blurred by a Gaussian of standard deviation ``field_blur``
    metres (``scipy.ndimage.gaussian_filter``, truncated at 2 sigma) and takes the place of the
    unblurred one: an occupied voxel then holds ``log_p_unobserved`` plus its blurred value (and
    its descriptor similarity, not blurred), any other voxel its free-space or unobserved value
    plus the blurred value. Blurred values under 0.02 nats are dropped, so that deep free space
    keeps exactly ``c_empty`` and distant cells their uniform fast paths. Unobserved voxels
    that received a value become ``EMPTY_CODE`` voxels (the kernel reads them from
    ``background``). With ``field_blur == 0`` the arrays are returned unchanged.

    Only the classifier's term is spread: blurring the free-space values as well flattened the
    mug's body as much but charged its handle ``c_empty`` up to a blur's width before it enters
    free space (``examples/benchmarks/bench_arc.py``: the handle's share varied by 8-30 nats inside the
    arc); blurring the free-space values alone, or the classifier's positives alone, left the
    body's roughness at 17-26 nats: it comes from the occupied shell and its negatives.

    Parameters
    ----------
    index : (X, Y, Z) ndarray of int32
        Row of ``logp`` at occupied voxels, ``EMPTY_CODE`` or ``UNOBSERVED_CODE`` elsewhere.
    background : (X, Y, Z) ndarray
        Values at the voxels that are not occupied (:func:`free_space_values`).
    logp : (M,) ndarray
        ``log p_O`` of the occupied voxels.
    voxel_size : float
        Metres.
    params : LikelihoodParams

    Returns
    -------
    index, background, logp
        New arrays (the inputs are not modified), same shapes.
    """
    from certpose.model._kernels import EMPTY_CODE, UNOBSERVED_CODE

    sigma = float(params.field_blur) / float(voxel_size)
    if sigma == 0.0:
        return index, background, logp
    from scipy.ndimage import gaussian_filter

    # The classifier's term relative to unobserved space, 0 off the occupied voxels: blurred
    # and added back, it spreads each surface voxel's evidence over its neighbours.
    occ = index >= 0
    part = np.zeros(background.shape)
    part[occ] = logp[index[occ]] - params.log_p_unobserved
    spread = gaussian_filter(part, sigma=sigma, mode="constant", cval=0.0, truncate=2.0)
    # Below 0.02 nats the spread is dropped: the cells it would touch keep their uniform
    # fast paths (about 10% of the point look-ups more in mixed cells without the cut).
    spread[np.abs(spread) < 0.02] = 0.0
    field = background + spread
    field[occ] = params.log_p_unobserved + spread[occ]
    new_logp = logp.copy()
    new_logp[index[occ]] = field[occ]
    new_background = field
    new_background[occ] = background[occ]
    new_index = index.copy()
    new_index[(index == UNOBSERVED_CODE) & (spread != 0.0)] = EMPTY_CODE
    return new_index, np.ascontiguousarray(new_background), np.ascontiguousarray(new_logp)


def blurred_descriptors(
    index: NDArray[np.int32],
    background: NDArray[np.float64],
    desc: NDArray[np.float32],
    logp: NDArray[np.float64],
    voxel_size: float,
    params: LikelihoodParams,
) -> tuple[NDArray[np.int32], NDArray[np.float32], NDArray[np.float64]]:
    """Eq. (1)'s voxel rows with the scene descriptors spread by ``params.descriptor_blur``.

    The descriptors of the occupied voxels (0 elsewhere, the ``z_null`` of unobserved space) are
    blurred channel by channel by a Gaussian of standard deviation ``descriptor_blur`` metres
    (``scipy.ndimage.gaussian_filter``, truncated at 2 sigma, over the occupied voxels' bounding
    box widened by the Gaussian's reach). Because ``f^T z`` is linear in ``f``, a point's
    similarity on the blurred field is the Gaussian-weighted mean of its neighbours'
    similarities. Every voxel whose blurred descriptor has ``beta * |G * f| >= 0.02`` (the cut of
    :func:`blurred_terms`: smaller similarities are dropped) becomes a row: an occupied voxel
    keeps its ``logp``, any other voxel takes its ``background`` value (free-space or unobserved
    value, plus the classifier's spread) as its ``logp``, so the kernel reads it with the
    blurred descriptor like an occupied voxel. Rows are in Morton order of their voxels, like
    :class:`PoseLikelihood`'s. The memory of the rows grows with them (YCB-Video 0000/000001,
    whole frame: 3.3 times the occupied voxels at 3.5 mm, 5.9 times at 7.5 mm; ``d`` float32
    and one float64 each), and so does the work of the cells beside the surface, which blend
    8 descriptor products instead of a free-space or unobserved value (see
    ``LikelihoodParams.descriptor_blur``).

    Parameters
    ----------
    index : (X, Y, Z) ndarray of int32
        Row of ``desc`` / ``logp`` at occupied voxels, ``EMPTY_CODE`` or ``UNOBSERVED_CODE``
        elsewhere (after :func:`blurred_terms`).
    background : (X, Y, Z) ndarray
        Values at the voxels that are not occupied.
    desc : (M, d) ndarray of float32
        Descriptors of the occupied voxels.
    logp : (M,) ndarray
        ``log p_O`` of the occupied voxels (blurred or not).
    voxel_size : float
        Metres.
    params : LikelihoodParams

    Returns
    -------
    index, desc, logp
        New arrays (the inputs are not modified): ``index`` of the same shape, ``(M', d)``
        and ``(M',)`` rows with ``M' >= M``. With ``descriptor_blur == 0`` or ``beta == 0`` the
        arrays are returned unchanged.
    """
    sigma = float(params.descriptor_blur) / float(voxel_size)
    occ = index >= 0
    if sigma == 0.0 or params.beta == 0.0 or not occ.any():
        return index, desc, logp
    from scipy.ndimage import gaussian_filter

    # The Gaussian's reach in voxels (scipy: int(truncate * sigma + 0.5)); the work is done on
    # the occupied voxels' bounding box widened by it.
    reach = int(2.0 * sigma + 0.5)
    ijk = np.argwhere(occ)
    lo = np.maximum(ijk.min(axis=0) - reach, 0)
    hi = np.minimum(ijk.max(axis=0) + reach + 1, index.shape)
    box = tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))
    sub = index[box]
    sub_occ = sub >= 0
    # Candidates: within the reach of an occupied voxel (a cube, as the separable Gaussian's).
    from scipy.ndimage import maximum_filter

    cand = maximum_filter(sub_occ, size=2 * reach + 1, mode="constant", cval=False)
    rows = sub[sub_occ]
    vol = np.zeros(sub.shape, dtype=np.float32)
    blurred = np.empty((int(cand.sum()), desc.shape[1]), dtype=np.float32)
    for c in range(desc.shape[1]):
        vol[sub_occ] = desc[rows, c]
        blurred[:, c] = gaussian_filter(vol, sigma=sigma, mode="constant", cval=0.0, truncate=2.0)[cand]
    keep = sub_occ[cand] | (params.beta * np.linalg.norm(blurred, axis=1) >= 0.02)
    where = np.argwhere(cand)[keep]
    blurred = blurred[keep]
    order = _morton_order(where.astype(np.float64), 1.0)
    where, blurred = where[order], blurred[order]
    cells = tuple(where[:, k] + lo[k] for k in range(3))
    old = index[cells]
    new_logp = np.where(old >= 0, logp[np.maximum(old, 0)], background[cells])
    new_index = index.copy()
    new_index[cells] = np.arange(where.shape[0], dtype=np.int32)
    return new_index, np.ascontiguousarray(blurred), np.ascontiguousarray(new_logp, dtype=np.float64)


def _as_poses(T: ArrayLike) -> tuple[NDArray[np.float64], bool]:
    arr = as_float_array(T, "T")
    single = arr.ndim == 2
    if single:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"Expected `T` to have shape (4, 4) or (B, 4, 4), got {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError("`T` contains NaN or inf values.")
    return np.ascontiguousarray(arr), single


class PoseLikelihood:
    """Eq. (1) for one scene, one object and one classifier, compiled for fast batches.

    Parameters
    ----------
    scene : SceneField
        Fused scene: ``state`` (X, Y, Z) with UNOBSERVED=0 / EMPTY=1 / OCCUPIED=2 and
        ``descriptors`` (X, Y, Z, d), L2-normalised at occupied voxels.
    classification : ObjectClassification
        ``log_p`` (X, Y, Z) on the scene's grid (read at occupied voxels).
    object_model : ObjectModel
        Points ``p_i`` (N, 3) in the object frame and descriptors ``z_i`` (N, d). With
        ``areas`` (surface-sampled models), point ``i``'s term is weighted by
        ``w_i = areas[i] / voxel_size**2``: eq. (1) then sums over the surface, one unit per voxel
        face, however densely it is sampled.
    params : LikelihoodParams, optional

    Notes
    -----
    Descriptors are stored in float32 (the sums are accumulated in float64 per point), so
    values agree with a float64 evaluation to about 1e-6 relative.
    """

    def __init__(
        self,
        scene: Any,
        classification: ObjectClassification,
        object_model: ObjectModel,
        *,
        params: LikelihoodParams | None = None,
    ) -> None:
        from certpose.model._kernels import EMPTY_CODE, UNOBSERVED_CODE

        self.params = params or LikelihoodParams()
        self.grid = scene_grid_spec(scene)
        state = np.asarray(scene.state)
        desc = np.asarray(scene.descriptors)
        if desc.ndim != 4 or desc.shape[:3] != state.shape:
            raise ValueError(
                f"Expected `scene.descriptors` to have shape {(*state.shape, 'd')}, got {desc.shape}."
            )
        d = desc.shape[3]
        if object_model.descriptors.shape[1] != d:
            raise ValueError(
                f"Descriptor dimensions differ: object {object_model.descriptors.shape[1]}, scene {d}."
            )
        log_p = np.asarray(classification.log_p, dtype=np.float64)
        if log_p.shape != state.shape:
            raise ValueError(
                f"Expected `classification.log_p` to have the scene's grid shape {state.shape}, "
                f"got {log_p.shape}."
            )
        occ = np.flatnonzero(state.reshape(-1) == OCCUPIED)
        # Occupied voxels' rows in Morton order of their grid position: the (up to 8) voxels
        # around a point have nearby rows, fewer cache lines per look-up (measured: about 7%
        # less eq. (1) time on replayed MLE batches; same values).
        occ = occ[_morton_order(np.stack(np.unravel_index(occ, state.shape), axis=1).astype(np.float64), 1.0)]
        occ_desc = desc.reshape(-1, d)[occ]
        occ_logp = log_p.reshape(-1)[occ]
        if not np.all(np.isfinite(occ_desc)):
            raise ValueError("`scene.descriptors` contains NaN or inf values at occupied voxels.")
        if not np.all(np.isfinite(occ_logp)):
            raise ValueError("`classification.log_p` contains NaN or inf values at occupied voxels.")
        background = free_space_values(state, self.grid.voxel_size, resolve_free_space(self.params, scene))
        index = np.full(state.size, UNOBSERVED_CODE, dtype=np.int32)
        index[(state == EMPTY).reshape(-1)] = EMPTY_CODE
        index[occ] = np.arange(occ.size, dtype=np.int32)
        # One unobserved voxel of padding on each side lets the kernel skip bounds checks.
        self._index = np.pad(index.reshape(state.shape), 1, constant_values=UNOBSERVED_CODE)
        self._background = np.pad(background, 1, constant_values=self.params.log_p_unobserved)
        self._desc = np.ascontiguousarray(occ_desc, dtype=np.float32)
        # The unblurred index and log p_O, for with_object's other params.
        self._raw_index, self._raw_logp = self._index, np.ascontiguousarray(occ_logp, dtype=np.float64)
        self._index, self._background, self._logp = blurred_terms(
            self._raw_index, self._background, self._raw_logp, self.grid.voxel_size, self.params)
        self._raw_desc = self._desc
        self._dim = d
        self._index, self._desc, self._logp = blurred_descriptors(
            self._index, self._background, self._raw_desc, self._logp, self.grid.voxel_size, self.params)
        # The model's seen colours, for the colour of its unseen points (unseen_color="best").
        self._color_columns = getattr(getattr(scene, "backbone", None), "color_columns", None)
        self._palette = _palette(object_model.descriptors, self._color_columns)
        self._desc = self._with_unseen_color(self._desc)
        self._state = state
        self._scene = scene
        self._set_depth(resolve_free_space(self.params, scene))
        self._cells = _cell_codes(self._index, self._background, self.params.c_empty, self._depth_codes())
        self._pixels = _pixel_free_space(scene, self.params, self.grid.voxel_size)
        self._set_object(object_model)

    def with_object(self, object_model: ObjectModel, *,
                    params: LikelihoodParams | None = None) -> PoseLikelihood:
        """Eq. (1) of the same scene and classifier for another object model (e.g. a subsample
        of this one) and optionally other ``params``, sharing this one's scene arrays instead of
        gathering and checking them again (only the free-space values are recomputed for new
        ``params``). The colour credited to unseen points (``unseen_color="best"``) stays this
        likelihood's: the best match among the coloured points of the model it was built with,
        so that a subsample or a part of that model scores on the same scale."""
        import copy

        if object_model.descriptors.shape[1] != self._dim:
            raise ValueError(f"Descriptor dimensions differ: object "
                             f"{object_model.descriptors.shape[1]}, scene {self._dim}.")
        other = copy.copy(self)
        if params is not None and params != self.params:
            other.params = params
            background = free_space_values(self._state, self.grid.voxel_size,
                                           resolve_free_space(params, self._scene))
            other._index, other._background, other._logp = blurred_terms(
                self._raw_index, np.pad(background, 1, constant_values=params.log_p_unobserved),
                self._raw_logp, self.grid.voxel_size, params)
            other._index, other._desc, other._logp = blurred_descriptors(
                other._index, other._background, self._raw_desc, other._logp, self.grid.voxel_size, params)
            other._desc = other._with_unseen_color(other._desc)
            other._set_depth(resolve_free_space(params, self._scene))
            other._cells = _cell_codes(other._index, other._background, params.c_empty,
                                       other._depth_codes())
            other._pixels = _pixel_free_space(self._scene, params, self.grid.voxel_size)
        other._set_object(object_model)
        return other

    def _set_depth(self, params: LikelihoodParams) -> None:
        # Distances into free space for free_space_at="point" (the graded kernels).
        self._graded = params.graded_at_point
        if self._graded:
            depth, self._fs_start = free_space_depths(self._state, self.grid.voxel_size, params)
            self._depth = np.pad(depth, 1)  # the padding is unobserved: depth 0
        else:
            self._depth, self._fs_start = None, 0.0

    def _depth_codes(self) -> tuple[NDArray[np.float64], float, float, float] | None:
        if not self._graded:
            return None
        return self._depth, self._fs_start, self.params.free_space_ramp, self.params.log_p_unobserved

    def _set_object(self, object_model: ObjectModel) -> None:
        # Points in Morton (Z-curve) order: neighbours in memory stay neighbours in the grid
        # under any pose, which keeps the voxel look-ups cache-friendly.
        self._order = _morton_order(object_model.points, self.grid.voxel_size)
        self._inverse = np.argsort(self._order)
        self._points = np.ascontiguousarray(object_model.points[self._order], dtype=np.float64)
        z = object_model.descriptors[self._order]
        if self._imputes:
            # The extra column: 1 for the points without colour, which then read their
            # similarity with the model's seen palette from the scene's extra column.
            cols = self._color_columns
            blank = ~np.any(z[:, cols] != 0, axis=1)
            z = np.hstack([z, blank[:, None].astype(z.dtype)])
        self._z = np.ascontiguousarray(z, dtype=np.float32)
        # Area-weighted models count one unit per voxel face of surface (ObjectModel.areas).
        areas = getattr(object_model, "areas", None)
        weights = (np.ones(len(self._order)) if areas is None
                   else np.asarray(areas, dtype=np.float64)[self._order] / self.grid.voxel_size**2)
        self._weights = np.ascontiguousarray(weights, dtype=np.float64)
        self.num_points = int(self._points.shape[0])
        #: Sum of the point weights: the number of points for unweighted models.
        self.total_weight = float(self._weights.sum())
        self.centroid = object_model.points.mean(axis=0)
        self._set_visibility(object_model)

    def _set_visibility(self, object_model: ObjectModel) -> None:
        """The visibility table of the kernels' point order, or None (every point counts)."""
        from certpose.model.visibility import cached_visibility_table, scene_cameras

        self._vis = None
        cams = scene_cameras(self._scene)
        pixels = resolve_free_space(self.params, self._scene).free_space == "pixels"
        normals = getattr(object_model, "normals", None)
        if not (self.params.visibility and pixels) or cams.shape[0] == 0 or normals is None:
            return
        table = cached_visibility_table(object_model.points, normals,
                                        grazing=self.params.visibility_grazing)
        vtab = (np.zeros((self.num_points, 0), dtype=np.uint8) if table.table is None
                else np.ascontiguousarray(table.table[self._order]))
        self._vis = (np.ascontiguousarray(table.normals[self._order]), vtab, np.int64(table.faces),
                     cams, float(table.grazing))
        self.visibility_table = table

    @property
    def _imputes(self) -> bool:
        """Whether eq. (1) credits the model's unseen points with a colour similarity."""
        return self.params.unseen_color != "none" and self._palette is not None

    def _with_unseen_color(self, desc: NDArray[np.float32]) -> NDArray[np.float32]:
        """The scene's descriptor rows, with a last column holding each row's similarity with
        the model's seen palette (``unseen_color``) when unseen points are credited with it."""
        if not self._imputes:
            return desc
        beta = None if self.params.unseen_color == "best" else self.params.beta
        col = palette_similarity(desc, self._palette, self._color_columns, beta=beta)
        return np.ascontiguousarray(np.hstack([desc, col[:, None]]), dtype=np.float32)

    @property
    def visible(self) -> bool:
        """Whether eq. (1) weighs the points by their visibility (``LikelihoodParams.visibility``
        with cameras and normals)."""
        return self._vis is not None

    @property
    def point_weights(self) -> NDArray[np.float64]:
        """The points' weights in eq. (1) (N,), in the model's order (ones unless the model
        has :attr:`~certpose.geometry.objects.ObjectModel.areas`)."""
        return self._weights[self._inverse]

    def visibility(self, T: ArrayLike) -> NDArray[np.float64]:
        """Visibility ``v_i`` in ``[0, 1]`` (N,) of the model points (the model's order) at the
        pose ``T`` (4, 4): the largest over the scene's cameras, what eq. (1) weighs each
        point's terms by (ones when visibility is off; :mod:`certpose.model.visibility`)."""
        poses, single = _as_poses(T)
        if not single:
            raise ValueError(f"Expected `T` to have shape (4, 4), got {poses.shape}.")
        if self._vis is None:
            return np.ones(self.num_points)
        R, t = poses[0][:3, :3], poses[0][:3, 3]
        points = self._points[self._inverse]
        v = np.zeros(self.num_points)
        for c in self._vis[3]:
            v = np.maximum(v, self.visibility_table.visibility(points, R.T @ (c - t)))
        return v

    def visible_weight(self, T: ArrayLike) -> float:
        """Sum of the point weights times their visibility at the pose ``T`` (4, 4): the weight
        of the points eq. (1) scores by what the scene shows at that pose (``total_weight`` when
        visibility is off)."""
        if self._vis is None:
            poses, single = _as_poses(T)
            if not single:
                raise ValueError(f"Expected `T` to have shape (4, 4), got {poses.shape}.")
            return self.total_weight
        return float(np.sum(self.point_weights * self.visibility(T)))

    def _args(self) -> tuple[Any, ...]:
        p = self.params
        # The graded kernels (free_space_at="point") take the distances into free space too.
        extra = (self._depth, self._fs_start, p.free_space_ramp) if self._graded else ()
        if self._vis is not None:
            extra = self._vis
        return (
            self._points, self._weights, self._z, self._index, self._cells, self._background, self._desc,
            self._logp, self.grid.origin, 1.0 / self.grid.voxel_size, self.grid.offset,
            np.float32(p.beta), p.c_empty, p.log_p_unobserved, *extra,
        )

    def __call__(self, T: ArrayLike) -> float | NDArray[np.float64]:
        """Alias of :meth:`log_likelihood`."""
        return self.log_likelihood(T)

    def log_likelihood(self, T: ArrayLike) -> float | NDArray[np.float64]:
        """Eq. (1) at the pose(s) ``T``.

        Parameters
        ----------
        T : (4, 4) or (B, 4, 4) array_like
            ``T_scene_object`` poses (map object points into the scene frame).

        Returns
        -------
        float or (B,) ndarray
            Log-likelihood up to the constant ``-N log Z`` (nats).
        """
        kernels = compiled("certpose.model._kernels")
        eq1_batch = (kernels.eq1_batch_graded if self._graded else
                     kernels.eq1_batch_visible if self._vis is not None else kernels.eq1_batch)
        if self._pixels is not None:
            # The pixel kernel is loaded here, on the calling thread, not by the pool's threads.
            eq1_batch = functools.partial(_with_pixels, eq1_batch, self._pixels.batch_kernel(), self)

        poses, single = _as_poses(T)
        args = self._args()
        pool, n_threads = _pool()
        n_chunks = min(n_threads, poses.shape[0],
                       poses.shape[0] * max(self.num_points, 1) // _PARALLEL_MIN_TERMS)
        if n_chunks <= 1:
            out = eq1_batch(poses, *args)
        else:
            chunks = np.array_split(poses, n_chunks)
            # The calling thread takes the first chunk itself: one hand-off fewer per call.
            futures = [pool.submit(eq1_batch, c, *args) for c in chunks[1:]]
            first = eq1_batch(chunks[0], *args)
            out = np.concatenate([first, *(f.result() for f in futures)])
        return float(out[0]) if single else out

    def point_terms(self, T: ArrayLike) -> NDArray[np.float64]:
        """Per-point terms ``w_i log p_loc(q_i)`` (N,) at one pose ``T`` (4, 4), weighted as in
        eq. (1) (``w_i = 1`` unless the model has :attr:`~certpose.geometry.objects.ObjectModel.areas`);
        they sum to eq. (1)."""
        kernels = compiled("certpose.model._kernels")
        eq1_points = (kernels.eq1_points_graded if self._graded else
                      kernels.eq1_points_visible if self._vis is not None else kernels.eq1_points)

        poses, single = _as_poses(T)
        if not single:
            raise ValueError(f"Expected `T` to have shape (4, 4), got {poses.shape}.")
        out = eq1_points(poses[0], *self._args())
        if self._pixels is not None:
            out += self._free_charge() * self._weights * self._pixels.fractions(poses[0], self._points)
        return out[self._inverse]

    def _free_charge(self) -> float:
        """What a point fully in per-pixel free space pays on top of its voxel term."""
        return self.params.c_empty - self.params.log_p_unobserved


def _palette(descriptors: NDArray[np.float64], columns: slice | None) -> NDArray[np.float32] | None:
    """The colour blocks (P, c) of the model points that carry colour, or None (no colour block
    in the backbone, or no coloured point)."""
    if columns is None:
        return None
    blocks = np.asarray(descriptors)[:, columns]
    seen = np.any(blocks != 0, axis=1)
    if not seen.any() or seen.all():
        return None
    return np.ascontiguousarray(blocks[seen], dtype=np.float32)


def palette_similarity(descriptors: ArrayLike, palette: ArrayLike, columns: slice, *,
                       beta: float | None = None, chunk: int = 4096) -> NDArray[np.float32]:
    """For each scene descriptor row, the colour similarity of a point whose colour is one of a
    palette's, unknown which: the log-mean-exp ``log mean_j exp(beta s_j) / beta`` of its
    similarities ``s_j = f_v[columns] . palette[j]`` (the marginal of eq. (1)'s term under a
    uniform prior on the palette), or their largest (``beta=None``).

    Parameters
    ----------
    descriptors : (M, d) array_like
        Scene descriptor rows.
    palette : (P, c) array_like
        Colour blocks of the model points that some view saw (``c`` columns).
    columns : slice
        The colour block's columns of ``descriptors`` (``c`` of them).
    beta : float or None, optional
        Nats per unit of similarity (>= 0; 0 gives the mean); None: the largest similarity.
    chunk : int, optional
        Rows per matrix product (bounds the memory at ``chunk * P`` floats).

    Returns
    -------
    (M,) ndarray of float32
    """
    desc = np.asarray(descriptors, dtype=np.float32)
    pal = np.asarray(palette, dtype=np.float32)
    if pal.ndim != 2 or pal.shape[0] == 0:
        raise ValueError(f"Expected `palette` to have shape (P, c) with P >= 1, got {pal.shape}.")
    block = desc[:, columns]
    if block.shape[1] != pal.shape[1]:
        raise ValueError(f"The colour block has {block.shape[1]} columns, the palette {pal.shape[1]}.")
    if beta is not None and not (math.isfinite(beta) and beta >= 0):
        raise ValueError(f"`beta` must be finite and >= 0, got {beta}.")
    block = np.ascontiguousarray(block)
    out = np.zeros(desc.shape[0], dtype=np.float32)
    # Rows without colour (a scene point nobody coloured) have similarity 0 with every colour.
    rows = np.flatnonzero(np.any(block != 0, axis=1))
    step = int(chunk)
    for s in range(0, rows.size, step):
        r = rows[s:s + step]
        sim = block[r] @ pal.T  # float32: the likelihood stores descriptors so
        top = sim.max(axis=1)
        if beta is None:
            out[r] = top
        elif beta == 0:
            out[r] = sim.mean(axis=1)
        else:
            sim -= top[:, None]
            sim *= np.float32(beta)
            np.exp(sim, out=sim)
            out[r] = top + (np.log(sim.mean(axis=1, dtype=np.float64)) / beta).astype(np.float32)
    return out


def resolve_free_space(params: LikelihoodParams, scene: Any) -> LikelihoodParams:
    """``params`` with ``free_space="auto"`` resolved for ``scene``: ``"pixels"`` when the scene
    keeps its depth images (``SceneField.frames``) and no voxel grading option
    (``free_space_tolerance``, ``free_space_ramp``, ``free_space_from``) differs from its
    default, ``"voxels"`` otherwise. Other values are returned unchanged."""
    if params.free_space != "auto":
        return params
    pixels = bool(getattr(scene, "frames", ())) and not params.voxel_grading_changed
    return replace(params, free_space="pixels" if pixels else "voxels")


def _pixel_free_space(scene: Any, params: LikelihoodParams, voxel_size: float) -> Any:
    """The per-pixel free-space test of ``free_space="pixels"`` (None for voxels)."""
    params = resolve_free_space(params, scene)
    if params.free_space != "pixels":
        return None
    from certpose.model.freespace import PixelFreeSpace

    return PixelFreeSpace.from_scene(
        scene, tolerance=params.depth_tolerance + params.free_space_erosion * voxel_size,
        ramp=params.depth_ramp, window=params.depth_window)


def _with_pixels(eq1_batch: Any, free_batch: Any, lik: PoseLikelihood, poses: NDArray[np.float64],
                 *args: Any) -> NDArray[np.float64]:
    """``eq1_batch`` plus the per-pixel free-space charge (same chunking, same threads)."""
    out = eq1_batch(poses, *args)
    return out + lik._free_charge() * lik._pixels.weighted_sum(poses, lik._points, lik._weights,
                                                                kernel=free_batch)


def log_likelihood(
    scene: Any,
    classification: ObjectClassification,
    object_model: ObjectModel,
    T: ArrayLike,
    *,
    params: LikelihoodParams | None = None,
) -> float | NDArray[np.float64]:
    """Eq. (1) at the pose(s) ``T`` ((4, 4) or (B, 4, 4)); see :class:`PoseLikelihood`.

    Build a :class:`PoseLikelihood` once when evaluating many batches.
    """
    return PoseLikelihood(scene, classification, object_model, params=params).log_likelihood(T)
