r"""A certified mode set of weighted TLS: every pose within a margin of the best lies in listed regions.

What it proves
--------------
For a weighted TLS problem ``f(R, t) = sum_k w_k min(||R a_k + t - b_k||^2 / beta_k^2, cbar2)``
and the best cost ``U`` found (the candidates given, or a box centre met on the way), with
``m = margin * U``: **every pose whose cost is at most** ``U + m`` **lies in one of the listed
regions** (a rotation ball about the region's minimiser times a translation box, infinity norm,
about its translation). Nothing is claimed about the ordering of poses inside a region (the
near-ties within a basin are left unresolved); everything outside the regions is proved worse
than ``U + m``. The status is ``certified`` only when the branch and bound has decided every
box; a time limit ends it with ``time_limit`` and no regions.

How
---
A branch and bound over rotation vectors (cubes in ``[-pi, pi]^3``, cubes wholly outside the
``pi``-ball dropped: their rotations are inside it) times translations. The translation domain is
complete: a pose whose translation puts no source point within ``cbar beta_k`` of its target has
every term truncated, cost ``cbar2 sum w``, and is pruned as a whole when that exceeds ``U + m``.

Two lower bounds per box, the larger counts. (1) Groups: the source points are grouped by
position (eq. (2)'s candidates: one model point, several grid points). Over a rotation cube of
half-side ``sigma`` and a translation cube of half-width ``h``, a point ``a``'s image lies in the
ball of radius ``2 sin(min(sqrt(3) sigma, pi) / 2) ||a||`` about its image at the box centre,
plus the translation cube (the angle between two rotations is at most the distance of their
rotation vectors). Each group's minimum over that set is exact: over inlier subsets ``S`` with
weight ``A_S`` (``sum w_k / beta_k^2``), weighted mean ``m_S`` and cost ``k_S`` at that mean
(outliers at ``cbar2 w_k``), it is ``min_S k_S + A_S d(m_S, set)^2``, the subsets enumerated
once (:mod:`solvers.certify.groups`' tables), tried in increasing ``k_S`` until none can do
better, only those of terms the set can bring within their truncation radius. The sum over
groups bounds the box. (2) Rigid, on small boxes: each term's minorant over its set (the exact
quadratic for a term inlier throughout, ``cbar2 w_k`` for one outlier throughout, an affine
minorant along its centre's direction for one that crosses its truncation radius), summed and
minimised over the box's motions linearised about the centre (``exp(w) p = p + w x p + e``, the
remainder ``|e| <= |p| (theta^2 / 2 + theta^3 / 6)`` charged to each term): a convex quadratic
in six variables over a ball times a cube, bounded below at any point by its tangent plane's
least value over the set. The upper bound is the cost at the box centre.

Regions are seeded about the candidates within the margin and sized on poses sampled about them
(the farthest within a few margins: the border then lies where boxes of moderate size can be
pruned), sampled within 30 deg and again within 60 and 120 deg while the farthest reaches the
sampled edge and, sampled wider, lies beyond it: a ridge of near-optimal poses such as a body of revolution's ring then lies in one
or two wide regions instead of a chain of narrow ones, whose borders cost most of the boxes (the
large marker of YCB-Video: 7-24 s instead of 33 s to more than 60 s); a box that lies inside a region is dropped, one outside is pruned when its lower bound
exceeds ``U + m``, kept (undecided) when no source point moves more than ``resolution`` noise
bounds over it, or split in its rotation or its translation half, whichever moves the points
more (8 children). A box outside every region whose centre is within a margin above ``U + m``,
or that is kept, seeds one more region. At the end, kept boxes join the region they touch or form
their own. When ``U`` falls, the threshold falls with it, so earlier prunings stay valid.

A lower bound of the whole problem comes out too, whatever the status: the least lower bound of
the boxes in the regions, kept or still open (every other box is above ``U + m``), with the
literature's gap of the best pose. It does not resolve the near-ties inside the regions.
"""

from __future__ import annotations

import logging
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.certificate import relative_gap
from solvers.jit import compiled
from solvers.problem import WeightedTLSProblem

log = logging.getLogger(__name__)

__all__ = ["MODE_SET_KERNELS", "ModeRegion", "ModeSetParams", "ModeSetResult", "ModeSetStatus",
           "certify_mode_set"]

MODE_SET_KERNELS = ("solvers.certify._mode_kernels:box_bounds",)
"""The compiled kernel of :func:`certify_mode_set` (for :func:`solvers.jit.warm_up`)."""

_KERNELS = "solvers.certify._mode_kernels"
_BATCH = 4096  # boxes per kernel call
_THREADED = 512  # batches at least this large are split over the pool's threads


class ModeSetStatus(str, Enum):
    """Outcome of :func:`certify_mode_set`."""

    CERTIFIED = "certified"
    """Every box was pruned or lies in a listed region."""
    TIME_LIMIT = "time_limit"
    """The time limit came first: no regions are claimed."""
    BOX_LIMIT = "box_limit"
    """More boxes were kept than ``max_kept_boxes``: no regions are claimed."""
    NO_MARGIN = "no_margin"
    """Every term truncated costs at most ``U + m``: every pose is within the margin."""

    @property
    def success(self) -> bool:
        return self is ModeSetStatus.CERTIFIED


@dataclass(frozen=True)
class ModeSetParams:
    """Options of :func:`certify_mode_set`.

    Attributes
    ----------
    margin : float
        Relative margin: poses with cost at most ``(1 + margin) * U`` are covered by the regions.
    resolution : float
        A box is kept (not split) once no source point moves more than this many (smallest)
        noise bounds over it; smaller gives tighter regions and more boxes.
    time_limit : float or None
        Seconds of the search (a first run's compilation of its kernel is not counted);
        ``None``: no limit.
    max_kept_boxes : int
        Kept boxes beyond which the search stops (status ``box_limit``).
    threads : int
        Threads over which large batches of boxes are bounded (the kernel releases the GIL).
    couple_below : float
        Boxes over which no source point moves more than this many (smallest) noise bounds
        also get the rigid bound (it helps only on small boxes, and costs a 6x6 solve).
    """

    margin: float = 0.02
    resolution: float = 0.25
    time_limit: float | None = 10.0
    max_kept_boxes: int = 200_000
    threads: int = 2
    couple_below: float = 0.5

    def __post_init__(self) -> None:
        if not (math.isfinite(self.margin) and self.margin >= 0):
            raise ValueError(f"`margin` must be >= 0, got {self.margin}.")
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"`resolution` must be positive, got {self.resolution}.")
        if self.time_limit is not None and not (self.time_limit > 0):
            raise ValueError(f"`time_limit` must be positive or None, got {self.time_limit}.")
        if int(self.max_kept_boxes) < 1 or int(self.threads) < 1:
            raise ValueError(f"`max_kept_boxes` and `threads` must be >= 1, got "
                             f"{self.max_kept_boxes} and {self.threads}.")


@dataclass(frozen=True, eq=False)
class ModeRegion:
    """A region of poses: a rotation ball times a translation box.

    Attributes
    ----------
    rotation : (3, 3) ndarray
        The region's best pose's rotation (its centre).
    rotation_radius : float
        Radians: every rotation of the region is within this geodesic angle of ``rotation``.
    translation : (3,) ndarray
        The best pose's translation (units of the points).
    translation_half_width : float
        Every translation of the region is within this of ``translation`` on each axis.
    cost : float
        The TLS cost at the best pose.
    num_boxes : int
        Kept boxes the region holds.
    """

    rotation: NDArray[np.float64]
    rotation_radius: float
    translation: NDArray[np.float64]
    translation_half_width: float
    cost: float
    num_boxes: int

    @property
    def T_target_source(self) -> NDArray[np.float64]:
        """(4, 4) the region's best pose."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.rotation, self.translation
        return T

    def contains(self, T: ArrayLike) -> bool:
        """Whether the pose ``T`` (4, 4) lies in the region."""
        T = np.asarray(T, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"Expected `T` to have shape (4, 4), got {T.shape}.")
        return (_angle(self.rotation, T[:3, :3]) <= self.rotation_radius + 1e-9
                and float(np.abs(T[:3, 3] - self.translation).max())
                <= self.translation_half_width + 1e-12)

    def moved(self, T_left: ArrayLike) -> ModeRegion:
        """The region of the poses ``T_left @ T`` (e.g. another frame's): the rotation ball moves
        with its centre; the translation box, turned by ``T_left``'s rotation, is replaced by the
        axis-aligned box that holds it."""
        T_left = np.asarray(T_left, dtype=np.float64)
        if T_left.shape != (4, 4):
            raise ValueError(f"Expected `T_left` to have shape (4, 4), got {T_left.shape}.")
        A = T_left[:3, :3]
        grow = float(np.abs(A).sum(axis=1).max())  # a cube of half-width 1, turned by A
        return ModeRegion(A @ self.rotation, self.rotation_radius,
                          A @ self.translation + T_left[:3, 3],
                          self.translation_half_width * grow, self.cost, self.num_boxes)

    def to_dict(self) -> dict[str, object]:
        return {"T_target_source": self.T_target_source.tolist(),
                "rotation_radius_deg": math.degrees(self.rotation_radius),
                "translation_half_width": self.translation_half_width, "cost": self.cost,
                "num_boxes": self.num_boxes}


@dataclass(frozen=True, eq=False)
class ModeSetResult:
    """Result of :func:`certify_mode_set`.

    Attributes
    ----------
    success : bool
        True when the mode set is certified.
    status : ModeSetStatus
    message : str
    regions : tuple of ModeRegion
        Best first; empty unless certified. Every pose of cost ``<= best_cost + margin`` lies in
        one of them.
    T_target_source : (4, 4) ndarray
        The best pose found (the first region's centre when certified).
    best_cost : float
        ``U``, the cost of ``T_target_source``.
    margin : float
        The absolute margin ``m`` (the problem's cost units).
    lower_bound : float
        A lower bound on the problem's minimum (sound whatever the status).
    literature_gap : float
        ``(U - lower) / (1 + |U| + |lower|)``.
    boxes_explored : int
        Boxes bounded.
    boxes_kept : int
        Boxes left undecided at the resolution (each joined to a region).
    solve_time : float
        Seconds.
    """

    success: bool
    status: ModeSetStatus
    message: str
    regions: tuple[ModeRegion, ...]
    T_target_source: NDArray[np.float64]
    best_cost: float
    margin: float
    lower_bound: float
    literature_gap: float
    boxes_explored: int
    boxes_kept: int
    solve_time: float

    def contains(self, T: ArrayLike) -> bool:
        """Whether the pose ``T`` (4, 4) lies in one of the regions."""
        return any(r.contains(T) for r in self.regions)

    def moved(self, T_left: ArrayLike) -> ModeSetResult:
        """The result for the poses ``T_left @ T`` (see :meth:`ModeRegion.moved`)."""
        from dataclasses import replace

        T_left = np.asarray(T_left, dtype=np.float64)
        return replace(self, regions=tuple(r.moved(T_left) for r in self.regions),
                       T_target_source=T_left @ self.T_target_source)

    def to_dict(self) -> dict[str, object]:
        return {"success": self.success, "status": self.status.value, "message": self.message,
                "regions": [r.to_dict() for r in self.regions],
                "T_target_source": self.T_target_source.tolist(), "best_cost": self.best_cost,
                "margin": self.margin, "lower_bound": _finite(self.lower_bound),
                "literature_gap": _finite(self.literature_gap),
                "boxes_explored": self.boxes_explored,
                "boxes_kept": self.boxes_kept, "solve_time": self.solve_time}


def _finite(x: float) -> float | None:
    """JSON has no inf or NaN: ``None`` for them."""
    return float(x) if math.isfinite(x) else None


def _angle(R1: NDArray[np.float64], R2: NDArray[np.float64]) -> float:
    c = (float(np.trace(R1.T @ R2)) - 1.0) / 2.0
    return math.acos(min(1.0, max(-1.0, c)))


def _rotvec_matrices(v: NDArray[np.float64]) -> NDArray[np.float64]:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(v).as_matrix().reshape(-1, 3, 3)


@dataclass(frozen=True, eq=False)
class _Tables:
    """The problem in the kernel's layout (centred coordinates, see :func:`_tables`)."""

    group_src: NDArray[np.float64]
    sub_start: NDArray[np.int64]
    sub_centre: NDArray[np.float64]
    sub_weight: NDArray[np.float64]
    sub_const: NDArray[np.float64]
    sub_mask: NDArray[np.int64]
    cap: NDArray[np.float64]
    term_start: NDArray[np.int64]
    term_dst: NDArray[np.float64]
    term_tau: NDArray[np.float64]
    src: NDArray[np.float64]
    dst: NDArray[np.float64]
    a: NDArray[np.float64]
    wc: NDArray[np.float64]
    tau: NDArray[np.float64]  # cbar beta_k: the residual at which a term is truncated
    src_origin: NDArray[np.float64]  # c_a: sources are a - c_a
    dst_origin: NDArray[np.float64]  # o_b: targets are b - o_b
    radius: float  # largest ||a - c_a||

    def args(self) -> tuple[NDArray, ...]:
        return (self.group_src, self.sub_start, self.sub_centre, self.sub_weight, self.sub_const,
                self.sub_mask, self.cap, self.term_start, self.term_dst, self.term_tau, self.src, self.dst, self.a, self.wc, self.tau)


def _tables(problem: WeightedTLSProblem) -> _Tables:
    """Groups of correspondences by source point, each group's inlier subsets sorted by their
    cost (those that cannot beat the all-outlier cost dropped). Internally a pose is ``(R, u)``
    with ``R (a - c_a) + u`` compared to ``b - o_b``, so ``t = u + o_b - R c_a``."""
    from solvers.certify.groups import ENUMERATE_MAX, _chunks, _subset_tables

    live = problem.weights > 0
    src_all, dst_all = problem.source[live], problem.target[live]
    w = problem.weights[live]
    a = w / problem.noise_bound[live] ** 2
    uniq, inv = np.unique(src_all, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    c_a = uniq.mean(axis=0)
    o_b = np.median(dst_all, axis=0)
    s, d = src_all - c_a, dst_all - o_b
    order = np.argsort(inv, kind="stable")
    starts = np.concatenate([[0], np.cumsum(np.bincount(inv, minlength=uniq.shape[0]))])
    pieces = []
    for g in range(uniq.shape[0]):
        idx = order[starts[g]:starts[g + 1]]
        pieces.extend(_chunks(d, idx) if idx.size > ENUMERATE_MAX else [idx])
    by_size: dict[int, list[NDArray[np.int64]]] = {}
    for idx in pieces:
        by_size.setdefault(int(idx.size), []).append(idx)
    gsrc, caps, centres, weights, consts, masks, tdst, ttau = [], [], [], [], [], [], [], []
    tau_all = np.sqrt(problem.cbar2) * problem.noise_bound[live]
    for _, group in sorted(by_size.items()):
        rows = np.stack(group)
        centre, weight, const = _subset_tables(d[rows], a[rows], w[rows], problem.cbar2)
        for r, idx in enumerate(group):
            cap = float(const[r, -1])
            keep = np.flatnonzero(const[r, :-1] < cap)
            keep = keep[np.argsort(const[r, keep], kind="stable")]
            gsrc.append(s[idx[0]])
            caps.append(cap)
            centres.append(centre[r, keep])
            weights.append(weight[r, keep])
            consts.append(const[r, keep])
            masks.append(keep + 1)  # subset codes: bit i for the group's i-th term
            tdst.append(d[idx])
            ttau.append(tau_all[idx])
    # Largest all-outlier costs first: a box's sum passes the threshold sooner.
    order = np.argsort(-np.asarray(caps), kind="stable")
    gsrc, caps = [gsrc[i] for i in order], [caps[i] for i in order]
    centres, weights = [centres[i] for i in order], [weights[i] for i in order]
    consts, masks = [consts[i] for i in order], [masks[i] for i in order]
    tdst, ttau = [tdst[i] for i in order], [ttau[i] for i in order]
    sub_start = np.concatenate([[0], np.cumsum([c.size for c in consts])]).astype(np.int64)
    return _Tables(np.ascontiguousarray(gsrc, dtype=np.float64), sub_start,
                   np.ascontiguousarray(np.concatenate(centres)),
                   np.ascontiguousarray(np.concatenate(weights)),
                   np.ascontiguousarray(np.concatenate(consts)),
                   np.concatenate(masks).astype(np.int64), np.asarray(caps, dtype=np.float64),
                   np.concatenate([[0], np.cumsum([x.shape[0] for x in tdst])]).astype(np.int64),
                   np.ascontiguousarray(np.concatenate(tdst)),
                   np.ascontiguousarray(np.concatenate(ttau)), np.ascontiguousarray(s),
                   np.ascontiguousarray(d), np.ascontiguousarray(a),
                   np.ascontiguousarray(w * problem.cbar2),
                   np.ascontiguousarray(tau_all), c_a, o_b,
                   float(np.linalg.norm(uniq - c_a, axis=1).max()))


def _initial_boxes(tab: _Tables, cbar: float, beta_max: float) -> NDArray[np.float64]:
    """Rotation cubes of half-side pi/4 that meet the pi-ball, times translation cubes covering
    every translation that leaves some term untruncated."""
    g = (np.arange(4) - 1.5) * (np.pi / 2)
    v = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    sigma = np.pi / 4
    near = np.linalg.norm(np.maximum(np.abs(v) - sigma, 0.0), axis=1)  # nearest point to 0
    v = v[near <= np.pi]
    reach = np.linalg.norm(tab.src, axis=1) + cbar * beta_max
    lo = (tab.dst - reach[:, None]).min(axis=0)
    hi = (tab.dst + reach[:, None]).max(axis=0)
    extent = hi - lo
    side = max(2.0 * tab.radius, 1e-12)
    n = np.maximum(np.ceil(extent / side), 1).astype(int)
    h = float((extent / (2 * n)).max())
    axes = [lo[i] + (np.arange(n[i]) + 0.5) * extent[i] / n[i] for i in range(3)]
    u = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    boxes = np.zeros((v.shape[0] * u.shape[0], 9))  # column 8: a lower bound known before
    boxes[:, :3] = np.repeat(v, u.shape[0], axis=0)
    boxes[:, 3] = sigma
    boxes[:, 4:7] = np.tile(u, (v.shape[0], 1))
    boxes[:, 7] = h
    return boxes


def _displacements(boxes: NDArray[np.float64], radius: float) -> tuple[NDArray, NDArray]:
    """Largest displacement of a source point over each box from rotation and translation."""
    rot = 2.0 * np.sin(0.5 * np.minimum(np.sqrt(3.0) * boxes[:, 3], np.pi)) * radius
    return rot, np.sqrt(3.0) * boxes[:, 7]


_CORNERS = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)


def _split(boxes: NDArray[np.float64], radius: float) -> NDArray[np.float64]:
    """8 children of each box, halving its rotation or its translation cube (the one that moves
    the points more); rotation cubes wholly outside the pi-ball are dropped."""
    rot, tr = _displacements(boxes, radius)
    out = []
    r = boxes[rot >= tr]
    if r.size:
        kids = np.repeat(r, 8, axis=0)
        kids[:, 3] *= 0.5
        kids[:, :3] += np.tile(_CORNERS, (r.shape[0], 1)) * kids[:, 3:4]
        near = np.linalg.norm(np.maximum(np.abs(kids[:, :3]) - kids[:, 3:4], 0.0), axis=1)
        out.append(kids[near <= np.pi])
    t = boxes[rot < tr]
    if t.size:
        kids = np.repeat(t, 8, axis=0)
        kids[:, 7] *= 0.5
        kids[:, 4:7] += np.tile(_CORNERS, (t.shape[0], 1)) * kids[:, 7:8]
        out.append(kids)
    return np.concatenate(out) if out else np.empty((0, 9))


class _Bounder:
    """Bounds batches of boxes with the compiled kernel, large batches over threads."""

    def __init__(self, tab: _Tables, threads: int, couple_rho: float) -> None:
        self._kernel = compiled(_KERNELS).box_bounds
        self._args = tab.args()
        self._couple = float(couple_rho)
        self._pool = ThreadPoolExecutor(max_workers=threads) if threads > 1 else None
        self._threads = threads

    def __call__(self, boxes: NDArray[np.float64],
                 threshold: float) -> tuple[NDArray, NDArray]:
        """Lower and upper bounds of each box; the rigid bound only where the groups' bound is
        at most ``threshold``."""
        boxes = np.ascontiguousarray(boxes)
        lower, upper = np.empty(boxes.shape[0]), np.empty(boxes.shape[0])
        args = (*self._args, float(threshold), self._couple)
        if self._pool is None or boxes.shape[0] < _THREADED:
            self._kernel(boxes, *args, lower, upper)
            return lower, upper
        cuts = np.linspace(0, boxes.shape[0], self._threads + 1).astype(int)
        futures = [self._pool.submit(self._kernel, boxes[a:b], *args, lower[a:b], upper[a:b]) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
        for f in futures:
            f.result()
        return lower, upper

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()


def _check_candidates(candidates: ArrayLike) -> NDArray[np.float64]:
    from solvers.validation import check_transform

    T = np.asarray(candidates, dtype=np.float64)
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] < 1:
        raise ValueError(f"Expected `candidates` to have shape (C, 4, 4) or (4, 4), got "
                         f"{np.shape(candidates)}.")
    return np.stack([check_transform(t, "candidates", atol=1e-6) for t in T])


def certify_mode_set(problem: WeightedTLSProblem, candidates: ArrayLike, *,
                     params: ModeSetParams | None = None,
                     rng: np.random.Generator | int | None = 0) -> ModeSetResult:
    """Prove that every pose within ``margin`` of the best cost lies in listed regions.

    Parameters
    ----------
    problem : WeightedTLSProblem
    candidates : (C, 4, 4) or (4, 4) array_like
        Poses ``T_target_source`` whose best cost starts the search (e.g. a solver's minimiser
        and its rivals); those within the margin seed the regions.
    params : ModeSetParams, optional
    rng : numpy Generator, int or None
        Seeds the sampling that sizes the regions about the seeds (the proof does not depend
        on it; a region sized too small is grown by the search).

    Returns
    -------
    ModeSetResult
        See the module docstring for what a certified result proves.
    """
    from solvers.validation import resolve_rng

    params = params or ModeSetParams()
    if not isinstance(problem, WeightedTLSProblem):
        raise TypeError(f"`problem` must be a WeightedTLSProblem, got {type(problem).__name__}.")
    T_c = _check_candidates(candidates)
    _load_kernel()  # a first run compiles it: not part of the search's time
    t0 = time.perf_counter()
    gen = resolve_rng(rng)
    costs = np.array([_cost(problem, T) for T in T_c])
    best = int(np.argmin(costs))
    U, T_best = float(costs[best]), T_c[best].copy()
    top = float(problem.cbar2 * problem.weights.sum())  # every term truncated
    tol = 1e-9 * (1.0 + top)  # rounding of a sum of K terms of at most `top`
    fraction = params.margin

    def result(status: ModeSetStatus, message: str, regions: tuple[ModeRegion, ...] = (),
               lower: float = float("nan"), explored: int = 0, kept: int = 0) -> ModeSetResult:
        lower = min(lower, U) if math.isfinite(lower) else lower
        gap = relative_gap(U, lower) if math.isfinite(lower) else float("inf")
        return ModeSetResult(status.success, status, message, regions, T_best, U,
                             fraction * abs(U), lower, gap, explored, kept,
                             time.perf_counter() - t0)

    if U + fraction * abs(U) + tol >= top:
        return result(ModeSetStatus.NO_MARGIN, f"the best cost {U:.6g} plus the margin reaches "
                      f"the all-outlier cost {top:.6g}: every pose is within the margin", lower=0.0)
    tab = _tables(problem)
    beta_min = float(problem.noise_bound[problem.weights > 0].min())
    threshold = U + fraction * abs(U) + tol
    regions = _seed_regions(problem, tab, T_c[np.argsort(costs)][np.sort(costs) <= threshold],
                            U, threshold, beta_min, gen)
    search = _search(problem, tab, regions, U, T_best, fraction, tol, beta_min, params, t0, gen)
    U, T_best = search.U, search.T_best
    threshold = U + fraction * abs(U) + tol
    if search.status is not ModeSetStatus.CERTIFIED:
        why = ("time limit" if search.status is ModeSetStatus.TIME_LIMIT
               else f"more than {params.max_kept_boxes} boxes kept")
        kept_lower = float(search.kept_lower.min()) if search.kept_lower.size else math.inf
        return result(search.status, f"{why} after {search.explored} boxes ({search.kept} "
                      "left undecided at the resolution): no mode set claimed",
                      lower=min(search.lower, kept_lower, threshold), explored=search.explored,
                      kept=search.kept)
    live = search.kept_lower <= threshold
    final = _final_regions(regions, search.kept_boxes[live], search.kept_upper[live], tab)
    lower = min([search.lower, *search.kept_lower[live].tolist()]) \
        if search.kept_lower[live].size else search.lower
    msg = (f"every pose of cost <= {threshold - tol:.6g} (best {U:.6g} + {100 * fraction:g}%) "
           f"lies in {len(final)} region(s); {search.explored} boxes bounded, "
           f"{int(live.sum())} left undecided at the resolution")
    log.debug("mode set: %s", msg)
    return result(ModeSetStatus.CERTIFIED, msg, final, lower=lower, explored=search.explored,
                  kept=int(live.sum()))


def _load_kernel() -> None:
    """Load (or, on a first run, compile) the kernel by calling it on no boxes."""
    e1, e2 = np.empty(0), np.empty((0, 3))
    i1 = np.zeros(1, dtype=np.int64)
    compiled(_KERNELS).box_bounds(np.empty((0, 9)), e2, i1, e2, e1, e1,
                                  np.empty(0, dtype=np.int64), e1, i1, e2, e1, e2, e2, e1, e1,
                                  e1, 0.0, 0.0, e1, e1)


def _cost(problem: WeightedTLSProblem, T: NDArray[np.float64]) -> float:
    return float(np.minimum(problem.residuals_sq(T[:3, :3], T[:3, 3]), problem.cbar2)
                 @ problem.weights)


@dataclass
class _Regions:
    """Regions in the search's coordinates: rotation balls times ``u`` boxes (infinity norm)."""

    R: NDArray[np.float64]  # (n, 3, 3)
    u: NDArray[np.float64]  # (n, 3)
    radius: NDArray[np.float64]  # (n,) radians
    half: NDArray[np.float64]  # (n,)
    cost: NDArray[np.float64]  # (n,)

    def add(self, other: _Regions) -> None:
        self.R = np.concatenate([self.R, other.R])
        self.u = np.concatenate([self.u, other.u])
        self.radius = np.concatenate([self.radius, other.radius])
        self.half = np.concatenate([self.half, other.half])
        self.cost = np.concatenate([self.cost, other.cost])

    def covers(self, boxes: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether each box lies wholly inside one region."""
        out = np.zeros(boxes.shape[0], dtype=bool)
        if self.R.shape[0] == 0 or boxes.shape[0] == 0:
            return out
        Rb = _rotvec_matrices(boxes[:, :3])
        ang = np.minimum(np.sqrt(3.0) * boxes[:, 3], np.pi)
        for j in range(self.R.shape[0]):
            cos = (np.einsum("ij,kij->k", self.R[j], Rb) - 1.0) / 2.0
            dang = np.arccos(np.clip(cos, -1.0, 1.0))
            # arccos near 1 is exact to about 1e-8 rad: keep that much away from the border.
            ok = (dang + ang <= self.radius[j] - 1e-7) & (
                np.abs(boxes[:, 4:7] - self.u[j]).max(axis=1) + boxes[:, 7] <= self.half[j])
            out |= ok
        return out


def _internal(T: NDArray[np.float64], tab: _Tables) -> NDArray[np.float64]:
    """``u`` of the pose ``T`` (search coordinates)."""
    return T[:3, 3] - tab.dst_origin + T[:3, :3] @ tab.src_origin


_SAMPLES = 4096  # poses sampled about each seed to size its region
_SAMPLE_ANGLE = math.radians(30.0)
_MAX_SAMPLE_ANGLE = math.radians(120.0)
_REACH_FULL = 0.8  # a farthest near-optimal sample this far out widens the sampling
_SIZE_MARGINS = 8.0
_MAX_REGIONS = 64
_SEED_MARGINS = 1.0  # a box centre this many margins above the threshold seeds a region


def _seed_regions(problem: WeightedTLSProblem, tab: _Tables, seeds: NDArray[np.float64],
                  best: float, threshold: float, beta: float,
                  gen: np.random.Generator) -> _Regions:
    """A region about each seed (best first, skipping seeds inside an earlier region), sized
    from sampled poses about it: 1.1 times the farthest sample within :data:`_SIZE_MARGINS`
    margins of the best, plus a little. Only a heuristic: the search covers whatever it
    leaves out; sized on the margin itself, the region's border would lie where the bounds
    are too loose to prune boxes of moderate size."""
    from scipy.spatial.transform import Rotation

    Rs, us, rr, hh, cc = [], [], [], [], []
    for T in seeds:
        u0 = _internal(T, tab)
        if any(_angle(R, T[:3, :3]) <= r and np.abs(u0 - u).max() <= h
               for R, u, r, h in zip(Rs, us, rr, hh, strict=True)):
            continue
        reach, sized = _SAMPLE_ANGLE, None
        while True:
            axis = gen.normal(size=(_SAMPLES, 3))
            axis /= np.linalg.norm(axis, axis=1, keepdims=True)
            ang = reach * gen.random(_SAMPLES) ** 2  # denser near the seed
            du = gen.uniform(-3 * beta, 3 * beta, size=(_SAMPLES, 3)) * gen.random((_SAMPLES, 1)) ** 2
            R = Rotation.from_rotvec(axis * ang[:, None]).as_matrix() @ T[:3, :3]
            moved = np.einsum("nij,kj->nki", R, tab.src) + (u0 + du)[:, None, :] - tab.dst
            f = np.minimum(tab.a * np.einsum("nki,nki->nk", moved, moved), tab.wc).sum(axis=1)
            ok = f <= best + _SIZE_MARGINS * (threshold - best)
            r_rot = float(ang[ok].max()) if ok.any() else 0.0
            r_tr = float(np.abs(du[ok]).max()) if ok.any() else 0.0
            if sized is not None and r_rot <= reach / 2:
                r_rot, r_tr = sized  # nothing near-optimal past the narrower sampling's edge
                break
            # Near-optimal poses up to the sampled reach and, sampled wider, beyond it: a ridge
            # (e.g. a symmetry's ring) that one wide region covers with less border to prune
            # than a chain of narrow ones.
            if r_rot < _REACH_FULL * reach or reach >= _MAX_SAMPLE_ANGLE:
                break
            sized, reach = (r_rot, r_tr), min(2.0 * reach, _MAX_SAMPLE_ANGLE)
        Rs.append(T[:3, :3].copy())
        us.append(u0)
        rr.append(1.1 * r_rot + math.radians(0.5))
        hh.append(1.1 * r_tr + 0.1 * beta)
        cc.append(_cost(problem, T))
    return _Regions(np.asarray(Rs).reshape(-1, 3, 3), np.asarray(us).reshape(-1, 3),
                    np.asarray(rr), np.asarray(hh), np.asarray(cc))


@dataclass
class _Search:
    status: ModeSetStatus
    U: float
    T_best: NDArray[np.float64]
    explored: int
    kept: int
    kept_boxes: NDArray[np.float64]
    kept_lower: NDArray[np.float64]
    kept_upper: NDArray[np.float64]
    lower: float  # least lower bound of the boxes covered by regions or left open


def _search(problem: WeightedTLSProblem, tab: _Tables, regions: _Regions, U: float,
            T_best: NDArray[np.float64], fraction: float, tol: float, beta: float,
            params: ModeSetParams, t0: float, gen: np.random.Generator) -> _Search:
    """The branch and bound: boxes are pruned (above the threshold), dropped (inside a
    region), kept (undecided at the resolution) or split. A box outside every region whose
    centre is within :data:`_SEED_MARGINS` margins above the threshold, or that is undecided
    at the resolution, seeds a new region (at most :data:`_MAX_REGIONS`)."""
    resolution = params.resolution * beta
    stack = [_initial_boxes(tab, math.sqrt(problem.cbar2), float(problem.noise_bound.max()))]
    kept_boxes, kept_lower, kept_upper = [], [], []
    explored = kept = 0
    covered_lower = float("inf")
    deadline = None if params.time_limit is None else t0 + params.time_limit
    bounder = _Bounder(tab, int(params.threads), params.couple_below * beta)
    status = ModeSetStatus.CERTIFIED
    try:
        while stack:
            if deadline is not None and time.perf_counter() > deadline:
                status = ModeSetStatus.TIME_LIMIT
                break
            boxes = stack.pop()
            if boxes.shape[0] > _BATCH:
                stack.append(boxes[_BATCH:])
                boxes = boxes[:_BATCH]
            lower, upper = bounder(boxes, U + fraction * abs(U) + tol)
            explored += boxes.shape[0]
            i = int(np.argmin(upper))
            if upper[i] < U:
                U = float(upper[i])
                T_best = _pose(boxes[i], tab)
            live = lower <= U + fraction * abs(U) + tol
            boxes, lower, upper = boxes[live], lower[live], upper[live]
            inside = regions.covers(boxes)
            thr = U + fraction * abs(U) + tol
            rot, tr = _displacements(boxes, tab.radius)
            # A centre within a few margins, or a box undecided at the resolution, outside
            # every region: the near-optimal set reaches there (e.g. along a symmetry's ring).
            fresh = ~inside & ((upper <= thr + _SEED_MARGINS * fraction * abs(U))
                               | (rot + tr <= resolution))
            if fresh.any() and regions.R.shape[0] < _MAX_REGIONS:
                k = int(np.flatnonzero(fresh)[np.argmin(upper[fresh])])
                regions.add(_seed_regions(problem, tab, _pose(boxes[k], tab)[None], U, thr,
                                          beta, gen))
                inside = regions.covers(boxes)
            if inside.any():
                covered_lower = min(covered_lower, float(lower[inside].min()))
                boxes, lower, upper = boxes[~inside], lower[~inside], upper[~inside]
            rot, tr = _displacements(boxes, tab.radius)
            small = rot + tr <= resolution
            if small.any():
                kept_boxes.append(boxes[small])
                kept_lower.append(lower[small])
                kept_upper.append(upper[small])
                kept += int(small.sum())
            if (~small).any():
                boxes[:, 8] = lower  # the children's bound until they have their own
                stack.append(_split(boxes[~small], tab.radius))
            if kept > params.max_kept_boxes:
                status = ModeSetStatus.BOX_LIMIT
                break
    finally:
        bounder.close()
    kb = np.concatenate(kept_boxes) if kept_boxes else np.empty((0, 9))
    kl = np.concatenate(kept_lower) if kept_lower else np.empty(0)
    ku = np.concatenate(kept_upper) if kept_upper else np.empty(0)
    # Every box pruned was above the threshold; the rest are covered, kept or still open
    # (carrying their parents' bounds): a sound lower bound on the whole problem.
    lows = [covered_lower, *(float(b[:, 8].min()) for b in stack if b.size)]
    return _Search(status, U, T_best, explored, kept, kb, kl, ku, min(lows))


def _pose(box: NDArray[np.float64], tab: _Tables) -> NDArray[np.float64]:
    """The pose ``T_target_source`` at a box's centre (original coordinates)."""
    R = _rotvec_matrices(box[None, :3])[0]
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = box[4:7] + tab.dst_origin - R @ tab.src_origin
    return T


def _components(boxes: NDArray[np.float64]) -> NDArray[np.int64]:
    """Label of each box: boxes that overlap or touch share one (transitively)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = boxes.shape[0]
    if n <= 1:
        return np.zeros(n, dtype=np.int64)
    s, h = float(boxes[:, 3].max()), float(boxes[:, 7].max())
    x = np.concatenate([boxes[:, :3] / (2 * s), boxes[:, 4:7] / (2 * h)], axis=1)
    pairs = cKDTree(x).query_pairs(1.0 + 1e-9, p=np.inf, output_type="ndarray")
    if pairs.size:
        i, j = pairs[:, 0], pairs[:, 1]
        touch = ((np.abs(boxes[i, :3] - boxes[j, :3]).max(axis=1)
                  <= (boxes[i, 3] + boxes[j, 3]) * (1 + 1e-9))
                 & (np.abs(boxes[i, 4:7] - boxes[j, 4:7]).max(axis=1)
                    <= (boxes[i, 7] + boxes[j, 7]) * (1 + 1e-9)))
        i, j = i[touch], j[touch]
    else:
        i = j = np.empty(0, dtype=np.int64)
    graph = coo_matrix((np.ones(i.size), (i, j)), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def _final_regions(regions: _Regions, boxes: NDArray[np.float64], upper: NDArray[np.float64],
                   tab: _Tables) -> tuple[ModeRegion, ...]:
    """The seeds' regions grown to hold the undecided boxes that touch them, and one more
    region (about its best box centre) per component of undecided boxes that touches none;
    reported in the original coordinates (``t = u + o_b - R c_a``: over a region ``t`` moves
    by its ``u`` half-width plus the chord of its radius times ``|c_a|``)."""
    R = [r.copy() for r in regions.R]
    u = [x.copy() for x in regions.u]
    rad, half, cost = list(regions.radius), list(regions.half), list(regions.cost)
    nbox = [0] * len(R)
    if boxes.shape[0]:
        labels = _components(boxes)
        Rb = _rotvec_matrices(boxes[:, :3])
        ang = np.minimum(np.sqrt(3.0) * boxes[:, 3], np.pi)
        for lab in np.unique(labels):
            idx = np.flatnonzero(labels == lab)
            # Join the first region the component touches (a box within its radius + the box's
            # own), else start a new region at the component's best box centre.
            j_hit = -1
            for j in range(len(R)):
                cos = (np.einsum("ij,kij->k", R[j], Rb[idx]) - 1.0) / 2.0
                dang = np.arccos(np.clip(cos, -1.0, 1.0))
                near = (dang <= rad[j] + ang[idx]) & (
                    np.abs(boxes[idx, 4:7] - u[j]).max(axis=1) <= half[j] + boxes[idx, 7])
                if near.any():
                    j_hit = j
                    break
            if j_hit < 0:
                k = idx[int(np.argmin(upper[idx]))]
                R.append(Rb[k].copy())
                u.append(boxes[k, 4:7].copy())
                rad.append(0.0)
                half.append(0.0)
                cost.append(float(upper[k]))
                nbox.append(0)
                j_hit = len(R) - 1
            cos = (np.einsum("ij,kij->k", R[j_hit], Rb[idx]) - 1.0) / 2.0
            reach = float((np.arccos(np.clip(cos, -1.0, 1.0)) + ang[idx]).max()) + 1e-7
            rad[j_hit] = max(rad[j_hit], reach)
            half[j_hit] = max(half[j_hit], float(
                (np.abs(boxes[idx, 4:7] - u[j_hit]).max(axis=1) + boxes[idx, 7]).max()))
            nbox[j_hit] += int(idx.size)
    c_norm = float(np.linalg.norm(tab.src_origin))
    out = []
    for j in range(len(R)):
        r = min(rad[j], np.pi)
        t = u[j] + tab.dst_origin - R[j] @ tab.src_origin
        out.append(ModeRegion(R[j], r, t, half[j] + 2 * math.sin(0.5 * r) * c_norm, cost[j],
                              nbox[j]))
    out.sort(key=lambda x: x.cost)
    return tuple(out)
