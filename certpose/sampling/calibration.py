"""A calibrated pose distribution: eq. (1)'s basins, reweighted, widened by the model's error.

Why not one temperature. On the shared YCB-Video frames (``examples/benchmarks/bench_calibration.py``) the
ground truth sits 20-800 nats of eq. (1) below the MLE even where the MLE is in the right basin
(the truth refined on eq. (1) climbs back to within 0-20 nats of the MLE, 2-14 deg and 2-5 mm away
from where it started: the model's systematic error), and in the wrong basin (a box's flip) the
truth's basin lies 100-400 nats below. A 6-D near-Gaussian target ``exp(eq. (1) / T)`` puts a pose
``g`` nats down at credible level ``chi2_6.cdf(2 g / T)``, so calibration needs ``T`` of a hundred
or more; but at such temperatures the target's mass is no longer near the object at all: poses
that put the object behind the observed surface or outside the scene's grid (every point
unobserved) are only about 700 nats below the MLE on a mug, and their volume (centimetres and
every rotation) outweighs the peak's (millimetres and degrees) by ``e^15`` or more, so at
``T = 100`` the importance sampler's best draws are 10-16 cm away (ESS 2-10 of 3,000; the
target is not even normalisable over an unbounded plateau). No temperature of eq. (1) alone
is calibrated.

What this builds instead (two scales, each with its own derivation, fitted on held-out scenes):

* **Basins.** The MLE's seeds (:func:`~certpose.sampling.sampler.seeds_from_mle`) and the half
  turns of the MLE pose about the model's three principal axes (refined locally on eq. (1)): the
  flips a geometry-only model cannot tell apart. Each basin ``k`` has its eq. (1) value ``L_k``.
* **Between basins**: mass ``∝ exp((L_k - L_max) / basin_temperature)``: eq. (1)'s preference
  between basins is as overconfident as its preference within one (the same correlated points,
  the same model errors), with its own temperature.
* **Within a basin**: the Laplace approximation of ``exp(eq. (1) / temperature)`` at the basin
  (``temperature`` = the sampler's default rule ``N / n_eff``) convolved with a *model error*
  ``N(0, diag(rotation_sigma^2 I, translation_sigma^2 I))`` in the tangent chart: the true pose
  is the pose the model explains best, moved by the model's own error (annotation and model
  geometry), independent of the data. With ``dof`` finite the component is a Student t with
  that scale instead (heavier tails). Its density is exact (a :class:`TangentMixture`).

The truth's credible level under the result is exact up to Monte Carlo error
(:meth:`CalibratedDistribution.credible_level`). How the defaults of :class:`CalibrationParams`
were fitted: :func:`fit_calibration` (the model error's scales from the median offset of the
truth from its nearest basin, then the basin temperature and ``dof`` on a grid by the training
pairs' coverage) on the 78 frame-object pairs (60 geometry-only, 18 cross-scene appearance
models) of the four shared YCB-Video scenes, eq. (1) with its default graded free space and the
Voronoi-area object models (``examples/benchmarks/bench_calibration.py --appearance --calibrated --fit
0000,0002,0049,0050``). The honest figure is held out: ``--loso`` fits on three
scenes and scores the fourth, every pair held out once. The truth lies inside the 90% / 50%
regions in (target 0.80-1.00 / 0.35-0.65):

* all 78 pairs 0.83 / 0.60; geometry-only 0.80 / 0.57, appearance 0.94 / 0.72;
* per scene 0000 1.00 / 0.87, 0002 0.89 / 0.81, 0049 0.60 / 0.53, 0050 0.81 / 0.19
  (the folds fit 1.67-2.00 deg, 1.12-1.37 mm, t with 3-5 dof, basin temperature 30-50).

With equal-area object models (``area_weights="equal"``) the same held-out
figures were 0.85 / 0.50 (geometry-only 0.82 / 0.45, appearance 0.94 / 0.67) and the defaults
1.63 deg, 1.26 mm, basin temperature 100.

Two scenes against two (``--fit 0000,0002`` and the swap) give 0.53 / 0.08 on 0049+0050 and
0.90 / 0.74 on 0000+0002: the scenes differ more than a fit on two of them can know. Right-basin
offsets are larger in 0049/0050 (median translation 2.2 / 3.0 mm against 1.5 / 1.7 mm in
0000/0002, rotation 4.2 deg in 0049 against 2.6-2.8 deg elsewhere; most objects of 0050, the
boxes and the drill included, are 2.5-5 mm off), and 7 of their 36 pairs have no basin within
30 deg of the truth (a tuna can 32-42 deg and a tomato can 52-55 deg about their axes, the bowl
47-68 deg), against none of 0000/0002's 42. The per-pair
covariates tried do not remove the scene effect: the offsets correlate with the basin's Laplace
width (log-log r 0.47 rotation, 0.56 translation) and with eq. (1) per model point at the MLE
(r -0.59 with the translation offset), hardly with object size, depth or visible pixels
(|r| <= 0.39); a model error proportional to the Laplace covariance (plus a floor, fitted by
maximum likelihood) or scaled by the per-point fit made one split better only by making the
other worse (held out 0.42 / 0.08 and 0.93 / 0.79; 0.58 / 0.17 and 0.98 / 0.86; the first
0.87 / 0.50 one scene at a time, no better), so the error stays one isotropic scale.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from certpose.sampling.distribution import PoseDistribution
from certpose.sampling.sampler import (
    ISParams,
    TangentMixture,
    _check_seeds,
    _laplace_covariances,
    _laplace_precisions,
    default_temperature,
    principal_half_turns,
)
from solvers.validation import resolve_rng

__all__ = ["Basins", "CalibratedDistribution", "CalibrationFit", "CalibrationParams",
           "calibrated_distribution", "find_basins", "fit_calibration"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationParams:
    """Knobs of :func:`calibrated_distribution` (fitted: see the module docstring).

    Defaults: :func:`fit_calibration` on all 78 pairs of the four shared YCB-Video scenes, eq. (1)
    with its graded free space and Voronoi-area object models (``examples/benchmarks/bench_calibration.py
    --appearance --calibrated --fit 0000,0002,0049,0050``): model error 1.65 deg and
    1.26 mm per axis (from the median offset of the truth from its basin over the 74 pairs whose
    basin was found; Student t with 3 dof), basin temperature 30 nats (the lowest of the grid
    whose training fit is tied with the best; training coverage 0.88 / 0.50 inside the 90% / 50%
    regions). Held out, one scene at a time (``--loso``): 0.83 / 0.60 over the 78 pairs; see the
    module docstring for the splits.

    Attributes
    ----------
    rotation_sigma : float
        Standard deviation of the model error per rotation axis (rad).
    translation_sigma : float
        Standard deviation of the model error per translation axis (m).
    basin_temperature : float
        Temperature of eq. (1) between basins (nats; ``inf`` = every basin the same mass).
    dof : float
        Degrees of freedom of the components (> 2): multivariate Student t in the chart with
        the sum of the two covariances as scale matrix (``inf`` = Gaussian); heavy tails for a
        model error that is a few degrees on most objects and ten on some.
    flips : bool
        Add the MLE's half turns about the model's principal axes as basins.
    """

    rotation_sigma: float = math.radians(1.65)
    translation_sigma: float = 0.00126
    basin_temperature: float = 30.0
    dof: float = 3.0
    flips: bool = True

    def __post_init__(self) -> None:
        for name in ("rotation_sigma", "translation_sigma"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"Expected `{name}` to be positive and finite, got {v}.")
        if not self.basin_temperature > 0:
            raise ValueError(f"Expected `basin_temperature` > 0, got {self.basin_temperature}.")
        if not self.dof > 2:
            raise ValueError(f"Expected `dof` > 2 (inf = Gaussian), got {self.dof}.")


@dataclass(frozen=True, eq=False)
class Basins:
    """Local maxima of eq. (1) that a distribution is built on.

    Attributes
    ----------
    poses : (K, 4, 4)
        ``T_scene_object`` of each basin (near-duplicates removed).
    log_likelihood : (K,)
        Eq. (1) at each (nats).
    laplace_covariances : (K, 6, 6)
        Chart covariances of ``exp(eq. (1) / temperature)`` at each basin (rad^2, m^2).
    temperature : float
        The within-basin temperature of ``laplace_covariances``.
    """

    poses: NDArray[np.float64]
    log_likelihood: NDArray[np.float64]
    laplace_covariances: NDArray[np.float64]
    temperature: float


def _distinct(poses: NDArray[np.float64], values: NDArray[np.float64]) -> NDArray[np.intp]:
    """Indices of ``poses`` (best value first) with no better pose within 2 mm and 2 deg."""
    keep: list[int] = []
    for i in np.argsort(-values):
        if all(np.linalg.norm(poses[i, :3, 3] - poses[j, :3, 3]) > 2e-3
               or np.linalg.norm(Rotation.from_matrix(poses[j, :3, :3].T @ poses[i, :3, :3]).as_rotvec())
               > math.radians(2.0) for j in keep):
            keep.append(int(i))
    return np.asarray(keep, dtype=np.intp)


def find_basins(
    likelihood,  # noqa: ANN001 - a PoseLikelihood
    seeds: ArrayLike,
    *,
    flips: bool = True,
    temperature: float | None = None,
) -> Basins:
    """The basins of :func:`calibrated_distribution`: the seeds and, with ``flips``, the first
    seed's half turns about the model's principal axes, refined locally on eq. (1)
    (:func:`certpose.estimation.mle.refine_pose`; the seeds are kept as given), near-duplicates
    removed, each with its Laplace covariance at ``temperature`` (None = the sampler's default
    rule at the first seed).

    Parameters
    ----------
    likelihood : PoseLikelihood
    seeds : (K, 4, 4) or (4, 4) array_like
        ``T_scene_object``; the first one is the MLE.
    flips : bool
    temperature : float, optional

    Returns
    -------
    Basins
    """
    from certpose.estimation.mle import refine_pose

    T0 = _check_seeds(seeds)
    temp = float(temperature) if temperature is not None else default_temperature(likelihood, T0[0])
    if not (math.isfinite(temp) and temp > 0):
        raise ValueError(f"Expected `temperature` to be positive and finite, got {temperature}.")
    poses = [T for T in T0]
    values = list(np.asarray(likelihood(T0), dtype=np.float64))
    if flips:
        radius = float(np.linalg.norm(likelihood._points - likelihood._points.mean(0), axis=1).max())
        for F in principal_half_turns(likelihood, T0[0]):
            T, v, _ = refine_pose(likelihood, F, scale=radius)
            poses.append(np.asarray(T))
            values.append(float(v))
    P = np.stack(poses)
    v = np.asarray(values)
    keep = _distinct(P, np.where(np.isfinite(v), v, -np.inf))
    P, v = P[keep], v[keep]
    p = ISParams(laplace_inflation=1.0)
    C = _laplace_covariances(_laplace_precisions(likelihood, P, temp, p), p)
    return Basins(P, v, C, temp)


@dataclass(frozen=True, eq=False)
class CalibratedDistribution:
    """A calibrated pose distribution (see the module docstring): an exact mixture density.

    Attributes
    ----------
    mixture : TangentMixture
        One Gaussian per basin, covariance ``Laplace + model error``, weight by eq. (1) at
        ``basin_temperature``.
    basins : Basins
    params : CalibrationParams
    """

    mixture: TangentMixture
    basins: Basins
    params: CalibrationParams

    def sample(self, n: int, *, rng: np.random.Generator | int | None = None) -> PoseDistribution:
        """``n`` equally weighted draws as a :class:`PoseDistribution` (``T_scene_object``)."""
        if int(n) < 1:
            raise ValueError(f"Expected `n` >= 1, got {n}.")
        R, t = self.mixture.sample(int(n), resolve_rng(rng))
        return PoseDistribution(R, t, np.full(int(n), 1.0 / int(n)))

    def log_density(self, T: ArrayLike) -> NDArray[np.float64]:
        """(n,) exact log-density at poses ``T`` (n, 4, 4) (per unit Haar measure x m^3)."""
        T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
        return self.mixture.log_density(T[:, :3, :3], T[:, :3, 3])

    def credible_level(self, T: ArrayLike, *, draws: int = 4000,
                       rng: np.random.Generator | int | None = 0) -> float:
        """Highest-density credible level of the pose ``T`` (4, 4), or of the best of several
        poses (k, 4, 4) (e.g. a symmetric object's equivalents): the mass whose density exceeds
        the density there, estimated from ``draws`` exact draws (standard error
        ``sqrt(l (1 - l) / draws)``)."""
        at = float(np.max(self.log_density(T)))
        R, t = self.mixture.sample(int(draws), resolve_rng(rng))
        return float(np.mean(self.mixture.log_density(R, t) > at))


def calibrated_distribution(
    likelihood,  # noqa: ANN001 - a PoseLikelihood
    seeds: ArrayLike | None = None,
    *,
    basins: Basins | None = None,
    params: CalibrationParams | None = None,
) -> CalibratedDistribution:
    """The calibrated distribution of the pose on eq. (1)'s basins (see the module docstring).

    Parameters
    ----------
    likelihood : PoseLikelihood
    seeds : (K, 4, 4) array_like, optional
        ``T_scene_object`` seeds, the MLE first (:func:`~certpose.sampling.sampler.seeds_from_mle`).
    basins : Basins, optional
        Precomputed :func:`find_basins` (then ``seeds`` is not used).
    params : CalibrationParams, optional

    Returns
    -------
    CalibratedDistribution
    """
    p = params or CalibrationParams()
    if basins is None:
        if seeds is None:
            raise ValueError("Expected `seeds` or `basins`.")
        basins = find_basins(likelihood, seeds, flips=p.flips)
    v = basins.log_likelihood
    ok = np.isfinite(v)
    if not np.any(ok):
        raise ValueError("eq. (1) is -inf at every basin; check the seeds.")
    if math.isinf(p.basin_temperature):
        w = ok.astype(np.float64)
    else:
        w = np.where(ok, np.exp((np.where(ok, v, 0.0) - v[ok].max()) / p.basin_temperature), 0.0)
    keep = w > 1e-12 * w.max()
    err = np.diag([p.rotation_sigma**2] * 3 + [p.translation_sigma**2] * 3)
    mix = TangentMixture(basins.poses[keep, :3, :3].copy(), basins.poses[keep, :3, 3].copy(),
                         basins.laplace_covariances[keep] + err, w[keep] / w[keep].sum(), p.dof)
    return CalibratedDistribution(mix, basins, p)


@dataclass(frozen=True, eq=False)
class CalibrationFit:
    """Result of :func:`fit_calibration`.

    Attributes
    ----------
    params : CalibrationParams
        The fitted parameters.
    num_right : int
        Training cases whose truth lies within ``right_basin_deg`` of a basin (the model error's
        scales are fitted on these).
    table : tuple of (dof, basin_temperature, in_90, in_50)
        The training coverage (fraction of cases whose truth is inside the 90% / 50% regions) at
        every grid point.
    """

    params: CalibrationParams
    num_right: int
    table: tuple[tuple[float, float, float, float], ...]


def _nearest_offset(basins: Basins, truths: NDArray[np.float64]) -> tuple[float, float]:
    """(rotation (rad), translation (m)) offset of the best of ``truths`` from its nearest basin
    (1 deg counted as 1 cm)."""
    best = (math.inf, math.inf)
    for T in truths:
        for B in basins.poses:
            w = float(np.linalg.norm(Rotation.from_matrix(B[:3, :3].T @ T[:3, :3]).as_rotvec()))
            d = float(np.linalg.norm(T[:3, 3] - B[:3, 3]))
            if w + d / 0.01 * math.radians(1) < best[0] + best[1] / 0.01 * math.radians(1):
                best = (w, d)
    return best


def fit_calibration(
    cases: Sequence[tuple[Basins, ArrayLike]],
    *,
    basin_temperatures: Sequence[float] = (30, 50, 100, 150, 200, 300, 500, 1e3, math.inf),
    dofs: Sequence[float] = (math.inf, 5.0, 3.0),
    right_basin_deg: float = 30.0,
    draws: int = 1000,
    tie: float = 0.03,
) -> CalibrationFit:
    """:class:`CalibrationParams` fitted on training ``cases`` (the procedure of the defaults).

    The model error's scales come from the truths' offsets to their nearest basins (cases whose
    offset is under ``right_basin_deg``: a right basin): for an isotropic 3-D error with ``nu``
    degrees of freedom ``|offset|^2 / sigma^2 ~ 3 F(3, nu)`` (``chi2_3`` for a Gaussian), so
    ``sigma = sqrt(median |offset|^2 / (3 F.ppf(0.5; 3, nu)))``, separately for rotation and
    translation. Then the basin temperature and ``nu`` from the grid ``basin_temperatures`` x
    ``dofs``: the point whose truth levels on the training cases come closest to uniform at 0.5
    and 0.9 (``|in 90% - 0.9| + |in 50% - 0.5|``, levels from ``draws`` exact draws at a fixed
    seed); among the points within ``tie`` of the best (Monte Carlo noise), the sharpest (the
    lowest basin temperature, then the most degrees of freedom).

    Parameters
    ----------
    cases : sequence of (Basins, (k, 4, 4) or (4, 4) array_like)
        Each training case's basins (:func:`find_basins`) and its true ``T_scene_object``, or the
        equivalent true poses of a symmetric object (the best one counts).
    basin_temperatures, dofs : sequence of float
        The grid (nats; degrees of freedom > 2, ``inf`` = Gaussian).
    right_basin_deg : float
        Offsets (deg) up to which a truth counts as in a found basin.
    draws : int
        Exact draws per credible level.
    tie : float
        Loss difference within which grid points count as tied.

    Returns
    -------
    CalibrationFit
    """
    from scipy.stats import f as f_dist

    if len(cases) == 0:
        raise ValueError("Expected at least one case in `cases`, got 0.")
    truths = [np.asarray(T, dtype=np.float64).reshape(-1, 4, 4) for _, T in cases]
    offsets = [_nearest_offset(b, T) for (b, _), T in zip(cases, truths, strict=True)]
    right = [(w, d) for w, d in offsets if w < math.radians(right_basin_deg)]
    if not right:
        raise ValueError(f"No case has its truth within `right_basin_deg` = {right_basin_deg} of a basin.")
    w2 = np.median([w**2 for w, _ in right])
    t2 = np.median([d**2 for _, d in right])
    fits, table = [], []
    for nu in dofs:
        q = 3 * f_dist.ppf(0.5, 3, nu if math.isfinite(nu) else 1e9)
        for tb in basin_temperatures:
            p = CalibrationParams(rotation_sigma=float(math.sqrt(w2 / q)), translation_sigma=float(math.sqrt(t2 / q)),
                                  basin_temperature=float(tb), dof=float(nu))
            lv = np.array([calibrated_distribution(None, basins=b, params=p).credible_level(T, draws=draws)
                           for (b, _), T in zip(cases, truths, strict=True)])
            in90, in50 = float(np.mean(lv <= 0.9)), float(np.mean(lv <= 0.5))
            table.append((float(nu), float(tb), in90, in50))
            fits.append((abs(in90 - 0.9) + abs(in50 - 0.5), p))
    best = min(loss for loss, _ in fits)
    ties = [p for loss, p in fits if loss <= best + tie]
    params = min(ties, key=lambda p: (p.basin_temperature, -p.dof))
    log.info("calibration fitted on %d cases (%d right-basin): %s", len(cases), len(right), params)
    return CalibrationFit(params, len(right), tuple(table))
