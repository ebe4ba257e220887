"""The noise-injected importance sampler of ``p(T) ∝ exp(eq. (1) / temperature)``.

Seeds (the MLE pose, the eq. (2) solutions, the MLE's other hypotheses and modes) are the centres
of a mixture of Gaussians in the tangent space of SE(3); every draw is weighted by the target
against the mixture's exact density; the mixture is refitted to the weighted draws for a few
rounds (adaptive importance sampling); the last round's draws form a :class:`PoseDistribution`.

Runs the seeds did not reach. A hidden handle leaves a flat arc of rotations about the mug's
axis, and often a second free run elsewhere on the circle (YCB-Video 0000: the handle behind the
foam brick) that eq. (1) rates as well as the arc. Which runs the MLE's poses land in depends on
its seed; a mixture adapted from them alone keeps to those runs (mass in the arc 0.80 with one
seed, 0.00 with another, on the same frame), and its tail draws that stray into a missed run
carry most of the weight (final ESS 9-250 of 10,000). So a few pilot rounds in
(``ISParams.sweep_rounds``) the heaviest components with a wide rotational direction are turned
the whole circle about the axis their covariance implies (:func:`_sweep`, 72 evaluations each);
the good turns that no component covers get components, each moved onto its ridge by a Newton
step on a finite-difference stencil and given the Laplace spread there (:func:`_newton_fit`).
Mixture weights follow the raw (not flattened) weighted draws, damped and floored, so that a new
component is not starved before it has been fitted. A pilot draw that holds more than 5% of its
round's weight far from every component (a narrow peak no sweep reached) gets a component of its
own, fitted the same way (:func:`_births`). ``examples/benchmarks/bench_is_seeds.py --seeds 0-9`` (demo and
YCB-V 0000/000001-5, 60 runs): final ESS < 1,000 in 33 runs before, none after (least 1,859).

Basins off the circle. A sweep turns about the axis of a run it has seen; a basin elsewhere (the
demo's mug upside down, a few tempered nats below the MLE) is reached only by tail draws, which
then carry the weight (the demo at seed 4: final ESS 563). With ``ISParams.half_turns`` the
first seed's half turns about the model's principal axes, refined on eq. (1)
(:func:`half_turn_seeds`), join the seeds when they are within ``half_turn_window`` tempered nats
of the best, each with a fixed initial share (``half_turn_share``); figures in :class:`ISParams`.
Such a basin can be a ring too (the upside-down mug spins as freely as the upright one), and its
light components draw too few pilot draws to widen along it, so the sweeps go per basin
(``ISParams.sweep_basins``): a flat component off every circle swept so far is swept as well.

Tangent chart (the one of :mod:`certpose.sampling.distribution`): around a centre ``(R_k, t_k)``
a 6-vector ``x = (w, d)`` is the pose ``R = R_k exp([w]_x)``, ``t = t_k + d`` (rotation vector in
radians, object-frame perturbation; translation in metres).

Proposal density (exact). A component draws ``x ~ N(0, S_k)`` (or a multivariate Student t
with scale ``S_k``, whose density replaces the Gaussian ``N`` below). The density of the resulting pose
with respect to the product of the Haar measure on SO(3) (normalised to agree with ``d^3 w`` at
the identity, total volume ``8 pi^2``) and Lebesgue measure on R^3 is

    q_k(R, t) = sum_{s in {theta + 2 pi m}} N((s u, d); 0, S_k) * s^2 / (2 (1 - cos theta)),

where ``theta u = log(R_k^T R)`` with ``theta`` in [0, pi]: ``2 (1 - cos s) / s^2`` is the
Jacobian of the exponential map of SO(3) (the Haar density in exponential coordinates), and the
sum over ``m`` (``|m| <= 1``, both signs of ``u`` covered by negative ``s``) collects every
rotation vector that maps to the same rotation. Nothing is estimated: the only truncation is the
wrap sum, whose neglected terms carry ``exp(-(3 pi)^2 / (2 sigma^2))`` of the mass (< 1e-19 for
rotation standard deviations up to 1 rad; for Student t components the neglected tail decays
polynomially: with 5 dof, 1e-4 of a component's mass at the 0.6 rad cap on its scale, 5e-7 at 0.2 rad).

Default temperature. At ``temperature = 1`` eq. (1) counts every object point as an independent
observation; neighbouring points look at the same voxels and their descriptors (FPFH over a
radius of several voxels) are strongly correlated. The default rule divides eq. (1) by the number
of object points per independent observation: ``temperature = temperature_scale * N / n_eff``,
with ``n_eff`` the number of distinct cells of side ``correlation_voxels`` voxels (default 4)
that the posed model occupies at the best seed (:func:`default_temperature`). This rule shapes
the distribution within a basin; its credible regions are *not* calibrated on YCB-Video (the
truth lies 20-800 nats below the MLE, and no single temperature of eq. (1) covers that without
the object's hidden poses swamping the target): :mod:`certpose.sampling.calibration` builds the
calibrated distribution (basins, a basin temperature and a model-error kernel) and says why.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation
from scipy.special import gammaln, logsumexp

from certpose.sampling.distribution import PoseDistribution
from solvers.jit import compiled
from solvers.lie import so3_log
from solvers.validation import resolve_rng

__all__ = ["ISParams", "ISResult", "TangentMixture", "default_temperature", "half_turn_seeds",
           "importance_sample", "perturbed_eq2_seeds", "principal_half_turns", "sample_pose_distribution",
           "seeds_from_mle"]

log = logging.getLogger(__name__)

LogTarget = Callable[[NDArray[np.float64]], NDArray[np.float64]]


def _progress(total: int, desc: str, enabled: bool):  # noqa: ANN202 - tqdm or a no-op
    if enabled:
        try:
            from tqdm.auto import tqdm

            return tqdm(total=total, desc=desc, leave=False)
        except ImportError:
            pass

    class _Log:
        def update(self, n: int = 1) -> None:
            pass

        def close(self) -> None:
            pass

    return _Log()


@dataclass(frozen=True)
class ISParams:
    """Knobs of :func:`importance_sample`.

    Attributes
    ----------
    draws : int
        Draws of the last round, which form the distribution.
    rounds : int
        Rounds (>= 1); each but the last draws ``pilot_draws`` and refits the mixture to them.
    pilot_draws : int
        Draws per adaptation round (0 = ``draws // 4``, at least 500).
    rotation_noise : float
        Initial standard deviation of the tangent rotation noise around each seed (rad).
    translation_noise : float
        Initial standard deviation of the translation noise (m).
    temperature : float or None
        Target ``exp(log_target / temperature)``; None = :func:`default_temperature` (only in
        :func:`sample_pose_distribution`; :func:`importance_sample` then uses 1).
    temperature_scale : float
        Multiplies the default temperature rule.
    correlation_voxels : float
        Side of the cells counted as independent observations by the default rule (voxels).
    defensive : float
        Fraction of the mixture kept at the initial seeds with the initial noise in every
        round (defensive importance sampling: bounds the weights where adaptation shrank too much). The
        defensive components are the initial ones (Laplace or isotropic).
    min_rotation_noise, min_translation_noise : float
        Floors on the adapted standard deviations (rad, m).
    resample : int
        Particles after resampling (0 = return the weighted draws).
    progress : bool
        Show a tqdm progress bar over rounds when tqdm is installed.
    dof : float
        Degrees of freedom of the components: multivariate Student t in the chart (``inf`` =
        Gaussian). The final round's ESS hangs on the proposal's tails (an arc of rotations the
        refits have not reached yet); t components with 5 dof raised the demo's least final ESS
        over 10 seeds from 1,238 to 1,989 and YCB-V 0000/000002's from 31 to 305.
    max_growth : float
        A refit may widen (or narrow) a component by at most this factor in standard deviation
        per round in any direction (> 1; narrowing is bounded by its square).
    max_rotation_noise, max_translation_noise : float
        Caps on the components' standard deviations in any direction (rad, m).
    laplace : bool
        Start each seed's component from a Laplace approximation (finite-difference Hessian of
        ``log_target / temperature``, 73 evaluations per seed) instead of the isotropic noise.
    laplace_step : float
        Finite-difference step in units of the initial noise (``rotation_noise``,
        ``translation_noise``): wide enough to smooth eq. (1)'s voxel-scale roughness.
    laplace_min, laplace_max : float
        The Laplace standard deviations are clipped to this range (units of the initial noise)
        in every eigendirection; directions with no downward curvature get ``laplace_max``.
    laplace_inflation : float
        Widens the clipped Laplace standard deviations (a proposal a little wider than the target).
    weight_damping : float
        A refit's mixture weights are this share of the old ones plus the rest of the mass its
        (raw) weighted draws give each component (in [0, 1)).
    min_component_weight : float
        Every adapted component keeps at least this share / K of the adapted mass (in [0, 1)).
    sweep_rounds : tuple of int
        After the refit of each of these pilot rounds (0-based), every adapted component whose
        widest rotational direction has a standard deviation of at least ``sweep_min_sd`` (a flat
        direction: a hidden handle's arc) is turned the whole circle about that direction, about
        the axis its covariance implies (:func:`_sweep`), and new components are placed on the
        turns within ``sweep_window`` nats (tempered) of the best value that the mixture does not
        cover. Without it, a run of good poses that no seed reached is found only by rare tail
        draws that carry most of the weight (the ESS collapses) or not at all (the mass depends
        on which runs the seeds happened to hit).
    sweep_step : float
        Grid step of the sweep (deg).
    sweep_min_sd : float
        Least standard deviation (deg) of a component's widest rotational direction to sweep it.
    sweep_window : float
        Turns within this many tempered nats of the best value seen get components.
    sweep_spacing : float
        New components sit at least this far apart along the swept circle (deg); it is also
        their standard deviation along it.
    sweep_components : int
        Components swept per sweep round in the heaviest basin (its heaviest with a flat
        direction): one of them may carry a poor estimate of the axis.
    sweep_max_new : int
        Components added per sweep round, at most (each costs a Newton fit and a share of every
        later mixture density).
    sweep_basins : int
        Basins swept per sweep round, at most (>= 1; 1 = every sweep in the heaviest basin, the
        former sampler). A flat component whose centre lies more than
        ``2 sweep_spacing`` of rotation or ``2 max_translation_noise`` from every turn of the
        sweeps so far starts a basin of its own: the heaviest of each such basin is swept once,
        about the axis of the Laplace fit at its centre (73 evaluations; its own refits rest on
        a dozen effective draws or none), with a budget of ``sweep_max_new`` components of its
        own. The demo's mug upside down is such a basin: a ring as the upright mug's arc,
        holding 1-6% of the mass, whose one or two half-turn components draw a few pilot draws
        per round and never widen along it; its draws between them carried the weight.
        ``examples/benchmarks/bench_is_seeds.py`` (the same cached MLE seeds, 1 -> 3): the demo
        at seeds 0-19, least final ESS 1,465 -> 3,241, 10% quantile 4,283 -> 4,319, median 6,154
        -> 5,874, largest Pareto k 0.77 -> 0.68 (mean 0.36 -> 0.38); the upside-down share of the
        weighted draws 0.2-4.7% -> 0.7-6.0% where the target's own is 0.8-5.7%
        (:func:`~certpose.sampling.reference.axis_marginal` about the upright truth and about the
        upside-down half turn, the ratio of their normalisers): the median ratio to it 0.44 ->
        0.80, the largest shortfall 3.2 points (seed 1: 0.5% of 3.7%) -> 1.2, the largest excess
        0 -> 1.6 points. YCB-Video 0000 frames 1-5 at seeds 0-4: bit for bit the same (no flat
        component off the first circle). Sampling time, 1 and 3 interleaved on one tree (load
        1.3-1.7): the demo 1.35 -> 1.53 s median (paired +0.14 s; 8-38 more components, about
        1,500 more evaluations), max 1.98 -> 1.81 s; YCB-Video unchanged.
        ``examples/benchmarks/bench_samplers.py --no-ycbv --seeds 0 1 2 3 4``: total variation from the
        target's exact marginal 0.034 0.030 0.037 0.033 0.048 -> 0.034 0.035 0.042 0.028 0.030
        (its own error 0.018); from the uniform on the rendered arc 0.060-0.106 -> 0.075-0.111,
        since the 1-4% now drawn upside down (0-1% before) lies off that arc.
    birth_weight : float
        A pilot draw holding more than this share of its round's weight, more than 3 standard
        deviations from its component, gets a component of its own (:func:`_births`; 1 = never).
        0.02 since the Voronoi-area object models, under which eq. (1) rates the
        mug's other hiding places closer to its arc: on YCB-Video 0000 frames 1-5, seeds 0-2,
        the least final ESS with 0.05 was 151 (frame 3, seed 0: the weight on a few stray draws
        in the run behind the foam brick), with 0.02 1,671.
    sweep_defensive : bool
        The swept components join the defensive ones too (as fitted, never refitted).
        ``examples/benchmarks/bench_is_seeds.py --seeds 0-9``, demo + YCB-V 0000/000001-5 (60 runs): with
        them final ESS median 3,815, 10% quantile 2,740, least 931 (1 run below 1,000: the demo
        at seed 9, a narrow peak no component reached); without them 3,568, 2,214, 1,192; the
        same arc figures and time (the mixture density is a small share of it).
    half_turns : bool
        :func:`sample_pose_distribution` also seeds the sampler with the first seed's half turns
        about the model's principal axes through its centroid, each refined on eq. (1)
        (:func:`half_turn_seeds`; the flips of :func:`certpose.sampling.calibration.find_basins`,
        climbed in one batch): a basin that no pilot round reaches, such as the demo's mug upside
        down (tilt 177 deg, its refined peak 3.6-5.3 tempered nats below the MLE on seeds 0-19,
        a ring of its own since its handle hides there too). Their cost (0.04-0.2 s) is counted
        in :attr:`ISResult.seconds`. ``examples/benchmarks/bench_is_seeds.py`` (the same MLE
        seeds off and on, ``--cache``): the demo at seeds 0-19, final ESS least 563 -> 1,465,
        10% quantile 3,379 -> 4,283, median 6,113 -> 6,154, runs under 1,000 1 -> 0 (seed 4 563 ->
        6,193; single seeds move both ways with the sampler's random path: seed 7 6,641 -> 3,739,
        seed 12 6,387 -> 1,465); YCB-Video 0000 frames 1-5 at seeds 0-4: their half turns lie
        18-102 tempered nats below the best seed, all but one beyond the window, so 24 of 25 runs
        are unchanged bit for bit and 000002 at seed 2 (a half turn 17.8 nats below) 2,399 -> 2,738.
        Without them the demo's sampler misses the upside-down basin on seeds 0, 10, 12 and 13
        (0-4 draws there; with them 89-278 draws and 0.2-4.7% of the mass: seed 12's 4.7% is what
        its ESS pays, 6,387 -> 1,465) and hits it with a few heavy tail draws on others (seed 4:
        67 draws, 5.2% of the weight). ``examples/benchmarks/bench_samplers.py --no-ycbv --seeds 0 1 2 3 4``:
        total variation of the marginal about the axis from the uniform on the rendered arc
        0.064-0.133 -> 0.060-0.106 (better on all five), from the target's exact marginal
        (``axis_marginal``, its own error 0.018) 0.034-0.044 -> 0.030-0.048 (better on four, seed
        4 0.034 -> 0.048), arc coverage the same, mass in it 0.88-0.96 -> 0.90-0.96. The default:
        without it the sampler leaves out up to 4.7% of the target's mass on
        some seeds, silently; with it the Pareto k of the final weights rises on some seeds (demo
        seeds 0-19: mean 0.31 -> 0.36, largest 0.55 -> 0.77, seed 18), and single runs lose ESS
        as above: the basin is a ring its one or two components under-cover (its share half the
        target's, median). ``sweep_basins`` (the default) covers it:
        largest Pareto k 0.68, least ESS 3,241. ``False`` gives the former sampler bit for bit.
    half_turn_window : float
        Refined half turns more than this many tempered nats below the best seed are dropped:
        such a basin holds about ``e^-20`` of the peak's mass, nothing a draw could find, and
        its seed only wastes draws and moves the adaptation's random path. Without the window
        (the half turns' shares by their value, about 0.2% each) YCB-Video 0000/000003 at seed 0
        fell from 2,178 to 543 and the demo at seed 8 from 2,856 to 157.
    half_turn_share : float
        Initial mixture share of each half-turn seed (the other seeds share the rest by their
        value at the seed, floored at 1%). By value the upside-down mug's seed would get about
        0.4% while it holds up to 4.7% of the mass: with window 20 and that share the demo at
        seed 4 ended at ESS 91, with 5% at 6,193.

    Notes
    -----
    Defaults measured on the demo mug (``examples/benchmarks/bench_sampler.py``): many cheap pilot rounds
    (11 x 500 draws) adapt more stably than a few large ones (5 x 2,500), and the Laplace start
    replaces an isotropic 3 mm noise that is about six times the target's translational spread.
    """

    draws: int = 10_000
    rounds: int = 12
    pilot_draws: int = 500
    rotation_noise: float = 0.03
    translation_noise: float = 0.003
    temperature: float | None = None
    temperature_scale: float = 1.0
    correlation_voxels: float = 4.0
    defensive: float = 0.1
    min_rotation_noise: float = 1e-3
    min_translation_noise: float = 1e-4
    resample: int = 0
    progress: bool = False
    max_growth: float = 2.0
    dof: float = 5.0
    laplace: bool = True
    laplace_step: float = 1.0
    laplace_min: float = 0.1
    laplace_max: float = 2.0
    laplace_inflation: float = 2.0
    max_rotation_noise: float = 0.6
    max_translation_noise: float = 0.01
    weight_damping: float = 0.5
    min_component_weight: float = 0.1
    sweep_rounds: tuple[int, ...] = (2, 4, 6, 8)
    sweep_step: float = 5.0
    sweep_min_sd: float = 4.0
    sweep_window: float = 10.0
    sweep_spacing: float = 15.0
    sweep_components: int = 3
    sweep_defensive: bool = True
    birth_weight: float = 0.02
    sweep_max_new: int = 8
    sweep_basins: int = 3
    half_turns: bool = True
    half_turn_window: float = 20.0
    half_turn_share: float = 0.05

    def __post_init__(self) -> None:
        if int(self.draws) < 2:
            raise ValueError(f"Expected `draws` >= 2, got {self.draws}.")
        if int(self.pilot_draws) < 0:
            raise ValueError(f"Expected `pilot_draws` >= 0, got {self.pilot_draws}.")
        if int(self.rounds) < 1:
            raise ValueError(f"Expected `rounds` >= 1, got {self.rounds}.")
        for name in ("rotation_noise", "translation_noise", "temperature_scale",
                     "min_rotation_noise", "min_translation_noise", "correlation_voxels",
                     "max_rotation_noise", "max_translation_noise"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"Expected `{name}` to be positive and finite, got {v}.")
        if self.temperature is not None and not (math.isfinite(self.temperature) and self.temperature > 0):
            raise ValueError(f"Expected `temperature` to be positive and finite, got {self.temperature}.")
        if not 0.0 <= self.defensive < 1.0:
            raise ValueError(f"Expected `defensive` in [0, 1), got {self.defensive}.")
        if not self.dof > 2:
            raise ValueError(f"Expected `dof` > 2 (inf = Gaussian), got {self.dof}.")
        if not (math.isfinite(self.max_growth) and self.max_growth > 1.0):
            raise ValueError(f"Expected `max_growth` > 1, got {self.max_growth}.")
        if int(self.resample) < 0:
            raise ValueError(f"Expected `resample` >= 0, got {self.resample}.")
        if not 0.0 < self.birth_weight <= 1.0:
            raise ValueError(f"Expected `birth_weight` in (0, 1], got {self.birth_weight}.")
        for name in ("weight_damping", "min_component_weight"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"Expected `{name}` in [0, 1), got {getattr(self, name)}.")
        for name in ("sweep_step", "sweep_min_sd", "sweep_window", "sweep_spacing"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"Expected `{name}` to be positive and finite, got {v}.")
        for name in ("sweep_components", "sweep_max_new", "sweep_basins"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"Expected `{name}` >= 1, got {getattr(self, name)}.")
        if not self.half_turn_window > 0:
            raise ValueError(f"Expected `half_turn_window` > 0 nats, got {self.half_turn_window}.")
        if not 0.0 < self.half_turn_share < 1.0 / 3.0:
            raise ValueError(f"Expected `half_turn_share` in (0, 1/3), got {self.half_turn_share}.")
        if any(int(r) < 0 for r in self.sweep_rounds):
            raise ValueError(f"Expected `sweep_rounds` >= 0, got {self.sweep_rounds}.")


def _so3_exp(w: NDArray[np.float64]) -> NDArray[np.float64]:
    return Rotation.from_rotvec(w).as_matrix()


_WRAPS = np.arange(-1, 2)
# The proposal density by certpose.sampling._kernels (the same arithmetic, compiled); False
# keeps the NumPy path, which the tests compare it with.
_COMPILED_DENSITY = True


@dataclass(frozen=True)
class TangentMixture:
    """A mixture of Gaussians in the tangent chart of SE(3) (see the module docstring).

    Attributes
    ----------
    rotations : (K, 3, 3)
        Component centres' rotations.
    translations : (K, 3)
        Component centres' translations (m).
    covariances : (K, 6, 6)
        Chart covariances (rad^2, m^2; rotation block first).
    weights : (K,)
        Mixture weights (sum to 1).
    dof : float
        Degrees of freedom (> 2): each component is a multivariate Student t in the chart with
        scale matrix ``covariances[k]``; ``inf`` (default) = Gaussian.
    """

    rotations: NDArray[np.float64]
    translations: NDArray[np.float64]
    covariances: NDArray[np.float64]
    weights: NDArray[np.float64]
    dof: float = math.inf

    def __post_init__(self) -> None:
        if not (self.dof > 2):
            raise ValueError(f"Expected `dof` > 2, got {self.dof}.")
        K = len(self.weights)
        if K == 0:
            raise ValueError("Expected at least one mixture component, got 0.")
        if self.rotations.shape != (K, 3, 3) or self.translations.shape != (K, 3) \
                or self.covariances.shape != (K, 6, 6):
            raise ValueError(
                f"Inconsistent component shapes: rotations {self.rotations.shape}, translations "
                f"{self.translations.shape}, covariances {self.covariances.shape}, weights ({K},).")
        if np.any(self.weights < 0) or not math.isclose(float(self.weights.sum()), 1.0, rel_tol=1e-9):
            raise ValueError("Expected mixture `weights` to be non-negative and sum to 1.")
        object.__setattr__(self, "_chol", np.linalg.cholesky(self.covariances))
        object.__setattr__(self, "_chol_inv", np.linalg.inv(self._chol))

    def sample(self, n: int, rng: np.random.Generator) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Draw ``n`` poses; returns rotations (n, 3, 3) and translations (n, 3)."""
        k = rng.choice(len(self.weights), size=n, p=self.weights)
        x = np.einsum("nij,nj->ni", self._chol[k], rng.standard_normal((n, 6)))
        if math.isfinite(self.dof):
            x *= np.sqrt(self.dof / rng.chisquare(self.dof, n))[:, None]
        R = np.einsum("nij,njk->nik", self.rotations[k], _so3_exp(x[:, :3]))
        return R, self.translations[k] + x[:, 3:]

    def log_density(self, R: ArrayLike, t: ArrayLike) -> NDArray[np.float64]:
        """Exact log-density (per unit Haar measure x m^3) at poses ``R`` (n, 3, 3), ``t`` (n, 3)."""
        return logsumexp(self.component_log_densities(R, t), axis=0)

    def component_log_densities(self, R: ArrayLike, t: ArrayLike) -> NDArray[np.float64]:
        """(K, n) ``log(weight_k q_k(R, t))``; their log-sum-exp over ``k`` is :meth:`log_density`."""
        R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
        t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
        n, K = len(R), len(self.weights)
        out = np.empty((K, n))
        # Each component's chart normaliser (t or Gaussian, its scale's determinant) and weight.
        log_norm = _t_log_norm(self.dof, 6) - np.log(np.diagonal(self._chol, axis1=1, axis2=2)).sum(axis=1)
        log_w = np.log(np.maximum(self.weights, 1e-300))
        if _COMPILED_DENSITY:
            kern = compiled("certpose.sampling._kernels").mixture_log_densities
            fixed = (np.ascontiguousarray(self.rotations), np.ascontiguousarray(self.translations),
                     np.ascontiguousarray(self._chol_inv), np.ascontiguousarray(log_norm),
                     np.ascontiguousarray(log_w), float(self.dof))
            kern(np.ascontiguousarray(R), np.ascontiguousarray(t), *fixed, out)
            return out
        for k in range(K):
            w = so3_log(np.einsum("ji,njk->nik", self.rotations[k], R), check=False)
            theta = np.linalg.norm(w, axis=1)
            u = np.where(theta[:, None] > 1e-12, w / np.maximum(theta, 1e-300)[:, None],
                         np.array([1.0, 0.0, 0.0]))
            # 2 (1 - cos theta), accurate near 0.
            two_one_minus_cos = np.maximum(4.0 * np.sin(theta / 2) ** 2, 1e-300)
            s = theta[:, None] + 2 * np.pi * _WRAPS[None, :]  # (n, M)
            # Whitened chart vector of wrap m: s_m A + B, with L^-1 split into its rotation and
            # translation columns (one product per component, not a solve per wrap).
            Li = self._chol_inv[k]
            A = u @ Li[:, :3].T
            B = (t - self.translations[k]) @ Li[:, 3:].T
            m2 = (s * s * np.sum(A * A, axis=1)[:, None] + 2.0 * s * np.sum(A * B, axis=1)[:, None]
                  + np.sum(B * B, axis=1)[:, None])
            if math.isfinite(self.dof):
                log_gauss = log_norm[k] - 0.5 * (self.dof + 6) * np.log1p(m2 / self.dof)
            else:
                log_gauss = log_norm[k] - 0.5 * m2
            # Near theta = 0 the m = 0 term's Jacobian ratio s^2 / (2 (1 - cos s)) -> 1.
            log_jac = np.where(s == 0, 0.0, np.log(np.maximum(s * s, 1e-300))
                               - np.log(two_one_minus_cos)[:, None])
            v = log_gauss + log_jac
            top = v.max(axis=1)
            out[k] = log_w[k] + top + np.log(np.exp(v - top[:, None]).sum(axis=1))
        return out


def _t_log_norm(nu: float, dim: int) -> float:
    """log normaliser of a standard ``dim``-variate Student t with ``nu`` degrees of freedom
    (``nu`` inf: the Gaussian's)."""
    if not math.isfinite(nu):
        return -0.5 * dim * math.log(2 * math.pi)
    return gammaln((nu + dim) / 2) - gammaln(nu / 2) - 0.5 * dim * math.log(nu * math.pi)


def _isotropic(rot: float, trans: float) -> NDArray[np.float64]:
    return np.diag([rot**2] * 3 + [trans**2] * 3)


@dataclass(frozen=True, eq=False)
class ISResult:
    """Output of :func:`importance_sample`.

    Attributes
    ----------
    distribution : PoseDistribution
        The last round's weighted draws (raw log-weights kept for Pareto-k), or their
        resampling when ``params.resample`` > 0.
    weighted : PoseDistribution
        The last round's weighted draws (always).
    proposal : TangentMixture
        The last round's proposal.
    temperature : float
    ess_per_round : tuple of float
    num_evaluations : int
        Target evaluations.
    seconds : float
        Wall-clock time of the sampling, the seeds' values and Laplace fits included (and, from
        :func:`sample_pose_distribution`, the half turns' search; not the seeds' own search,
        e.g. the MLE).
    success : bool
    status : str
        ``"ok"``, or ``"low_ess"`` when the final ESS is below 1% of the draws.
    message : str
    log_target : (n,) ndarray
        ``log_target`` (not divided by the temperature) at the draws of :attr:`weighted`, in
        its order: the target density up to a constant, which :meth:`credible_level` ranks.
    """

    distribution: PoseDistribution
    weighted: PoseDistribution
    proposal: TangentMixture
    temperature: float
    ess_per_round: tuple[float, ...]
    num_evaluations: int
    seconds: float
    status: str
    message: str
    log_target: NDArray[np.float64] = None  # type: ignore[assignment]

    @property
    def success(self) -> bool:
        return self.status == "ok"

    def credible_level(self, log_target_value: float) -> float:
        """Highest-density credible level of a pose whose ``log_target`` is ``log_target_value``.

        The highest-density region of ``exp(log_target / temperature)`` at level ``alpha`` is
        ``{T : log_target(T) > c}`` with mass ``alpha``; its mass above a given value is the
        importance-weighted mass of the draws whose target exceeds it. The target's own density
        ranks the poses (no kernel density: exact for multimodal targets, e.g. a box's flips,
        up to the Monte Carlo error of the weights), so a pose lies inside the ``alpha`` region
        iff the returned level is ``<= alpha``; for a calibrated distribution the level of the
        true pose is uniform on [0, 1].

        Parameters
        ----------
        log_target_value : float
            ``log_target`` at the pose (same units as :attr:`log_target`; ``-inf`` gives 1).

        Returns
        -------
        float
            In [0, 1].
        """
        v = float(log_target_value)
        if math.isnan(v):
            raise ValueError("Expected `log_target_value` to be a number, got nan.")
        return float(min(np.sum(self.weighted.weights[self.log_target > v]), 1.0))


def _check_seeds(seeds: ArrayLike) -> NDArray[np.float64]:
    T = np.asarray(seeds, dtype=np.float64)
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) == 0:
        raise ValueError(f"Expected `seeds` to have shape (K, 4, 4) with K >= 1, got {T.shape}.")
    if not np.all(np.isfinite(T)):
        raise ValueError("`seeds` contains NaN or infinite values.")
    err = np.abs(np.einsum("nji,njk->nik", T[:, :3, :3], T[:, :3, :3]) - np.eye(3)).max(axis=(1, 2))
    if np.any(err > 1e-6) or np.any(np.linalg.det(T[:, :3, :3]) < 0):
        raise ValueError("`seeds` contains a matrix whose rotation block is not a rotation.")
    return T


def _flattened(logw: NDArray[np.float64], fraction: float) -> tuple[NDArray[np.float64], float]:
    """Normalised weights ``w^a``, with the largest ``a`` in (0, 1] whose ESS is at least
    ``fraction`` of the draws: a refit on a handful of draws would collapse the covariance."""
    lw = np.where(np.isfinite(logw), logw, -np.inf)

    def norm_w(a: float) -> NDArray[np.float64]:
        v = np.exp(a * (lw - lw.max()))
        return v / v.sum()

    target = fraction * len(lw)
    if 1.0 / np.sum(norm_w(1.0) ** 2) >= target:
        return norm_w(1.0), 1.0
    lo, hi = 0.0, 1.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if 1.0 / np.sum(norm_w(mid) ** 2) >= target else (lo, mid)
    a = max(lo, 1e-6)
    return norm_w(a), a


def _with_defensive(adapted: TangentMixture, initial: TangentMixture, defensive: float) -> TangentMixture:
    """The proposal: the adapted components and, with mass ``defensive``, the initial ones."""
    if defensive == 0.0:
        return adapted
    return TangentMixture(
        np.concatenate([adapted.rotations, initial.rotations]),
        np.concatenate([adapted.translations, initial.translations]),
        np.concatenate([adapted.covariances, initial.covariances]),
        np.concatenate([adapted.weights * (1.0 - defensive), initial.weights * defensive]),
        adapted.dof,
    )


def _clip_in_metric(C: NDArray[np.float64], L: NDArray[np.float64], lo: float, hi: float) -> NDArray[np.float64]:
    """``C`` with the eigenvalues of ``L^-1 C L^-T`` clipped to [lo, hi]."""
    Li = np.linalg.inv(L)
    M = Li @ C @ Li.T
    lam, V = np.linalg.eigh(0.5 * (M + M.T))
    M = (V * np.clip(lam, lo, hi)) @ V.T
    return L @ M @ L.T


def _bounded(C: NDArray[np.float64], C_old: NDArray[np.float64], p: ISParams) -> NDArray[np.float64]:
    """A refitted covariance within a factor ``max_growth`` (in standard deviation, any direction)
    of the previous one, and within the absolute caps: a refit on heavy-tailed weights or the
    flattening correction can otherwise blow a component up to centimetres and tens of degrees,
    where the unobserved space's mass swamps the target and the ESS collapses."""
    g = float(p.max_growth) ** 2
    C = _clip_in_metric(C, np.linalg.cholesky(C_old), 1.0 / g, g)
    cap = np.diag([p.max_rotation_noise] * 3 + [p.max_translation_noise] * 3)
    return _clip_in_metric(C, cap, 0.0, 1.0)


def _stencil() -> NDArray[np.float64]:
    """(73, 6) unit offsets of the central-difference Hessian: 0, +-e_i, and +-e_i +-e_j (i < j)."""
    E = np.eye(6)
    pts = [np.zeros(6)] + [s * E[i] for i in range(6) for s in (1, -1)]
    pts += [a * E[i] + b * E[j] for i in range(6) for j in range(i + 1, 6) for a in (1, -1) for b in (1, -1)]
    return np.asarray(pts)


def _laplace_precisions(log_target: LogTarget, T0: NDArray[np.float64], temp: float,
                        p: ISParams) -> NDArray[np.float64]:
    """(K, 6, 6) ``-Hessian`` of ``log_target / temp`` at each seed in units of the initial noise
    (chart coordinates ``x = D u``, ``D = diag(rotation_noise, translation_noise)``), by central
    differences with a step of ``laplace_step`` noise units: wide enough to smooth eq. (1)'s
    voxel-scale roughness. 73 evaluations per seed, one batch."""
    st = _stencil()
    D = np.array([p.rotation_noise] * 3 + [p.translation_noise] * 3) * p.laplace_step
    K = len(T0)
    x = st * D  # (73, 6)
    T = np.tile(np.eye(4), (K, len(st), 1, 1))
    T[:, :, :3, :3] = np.einsum("kij,njl->knil", T0[:, :3, :3], _so3_exp(x[:, :3]))
    T[:, :, :3, 3] = T0[:, None, :3, 3] + x[None, :, 3:]
    f = np.asarray(log_target(T.reshape(-1, 4, 4)), dtype=np.float64).reshape(K, len(st)) / temp
    f = np.where(np.isfinite(f), f, np.nanmin(np.where(np.isfinite(f), f, np.nan)) - 100.0) \
        if np.any(np.isfinite(f)) else np.zeros_like(f)
    return _stencil_hessian(f, p)


def _stencil_hessian(f: NDArray[np.float64], p: ISParams) -> NDArray[np.float64]:
    """(K, 6, 6) ``-Hessian`` per noise unit squared from the stencil values ``f`` (K, 73)."""
    K = len(f)
    H = np.empty((K, 6, 6))
    for i in range(6):
        H[:, i, i] = f[:, 1 + 2 * i] - 2 * f[:, 0] + f[:, 2 + 2 * i]
    c = 13
    for i in range(6):
        for j in range(i + 1, 6):
            v = (f[:, c] - f[:, c + 1] - f[:, c + 2] + f[:, c + 3]) / 4.0
            H[:, i, j] = H[:, j, i] = v
            c += 4
    # Second differences over a step of `laplace_step` noise units -> per noise unit squared.
    return -H / p.laplace_step**2


def _laplace_covariances(P: NDArray[np.float64], p: ISParams) -> NDArray[np.float64]:
    """(K, 6, 6) initial chart covariances from the precisions of :func:`_laplace_precisions`:
    standard deviations clipped to [``laplace_min``, ``laplace_max``] noise units in every
    eigendirection (flat or curving-up directions, i.e. a seed off a maximum or a flat arc, get
    ``laplace_max``), widened by ``laplace_inflation`` (a proposal wider than the target)."""
    D = np.array([p.rotation_noise] * 3 + [p.translation_noise] * 3)
    lam, V = np.linalg.eigh(0.5 * (P + np.swapaxes(P, 1, 2)))
    lam = np.where(lam > 0, lam, 0.0)
    var = np.clip(1.0 / np.maximum(lam, 1e-300), p.laplace_min**2, p.laplace_max**2) * p.laplace_inflation**2
    C = np.einsum("kij,kj,klj->kil", V, var, V) * np.outer(D, D)
    return 0.5 * (C + np.swapaxes(C, 1, 2))


def _refit(proposal: TangentMixture, logs: NDArray, n_adapted: int, R: NDArray, t: NDArray,
           w: NDArray, alpha: float, p: ISParams, w_raw: NDArray | None = None) -> TangentMixture | None:
    """One adaptation step: the adapted components' weighted draws give their new centres and
    covariances (responsibilities from the whole proposal); None when no component has weight.

    Centres and covariances come from the flattened weights ``w``; the mixture weights from the
    raw ones ``w_raw`` (default ``w``), damped by ``weight_damping`` and floored at
    ``min_component_weight`` / K: flattened weights understate exactly the components whose
    few draws carry the most weight (a run the proposal under-covers), and a component given
    too little weight gets too few draws to grow."""
    resp = np.exp(logs - logsumexp(logs, axis=0))
    # Draws owned by the defensive components are shared among the adapted ones.
    resp_a = resp[:n_adapted] / np.maximum(resp[:n_adapted].sum(axis=0), 1e-300)
    w_raw = w if w_raw is None else w_raw
    old_w = proposal.weights[:n_adapted] / proposal.weights[:n_adapted].sum()
    Rs, ts, Cs, ws = [], [], [], []
    floor = _isotropic(p.min_rotation_noise, p.min_translation_noise)
    for k in range(n_adapted):
        wk = w * resp_a[k]
        mass = wk.sum()
        raw_mass = float(w_raw @ resp_a[k])
        mixed = p.weight_damping * old_w[k] + (1.0 - p.weight_damping) * raw_mass
        if mass <= 1e-12:
            if resp_a[k].sum() >= 1.0:
                continue  # its draws have no weight at all: drop the component
            # Hardly drawn: nothing to learn from, keep it.
            Rs.append(proposal.rotations[k])
            ts.append(proposal.translations[k])
            Cs.append(proposal.covariances[k])
            ws.append(mixed)
            continue
        if 1.0 / np.sum((wk / mass) ** 2) < 12:
            # Too few effective draws for a covariance: keep the spread, move the centre to the
            # weighted mean (a component half off the ridge it covers slides onto it; narrowing
            # it there, as a too-wide one would need, starves the ridge of draws).
            wk = wk / mass
            Rk = proposal.rotations[k]
            Rk = Rk @ _so3_exp(wk @ so3_log(np.einsum("ji,njk->nik", Rk, R), check=False))
            Rs.append(Rk)
            ts.append(wk @ t)
            Cs.append(proposal.covariances[k])
            ws.append(mixed)
            continue
        wk = wk / mass
        # A few Karcher steps from the old centre.
        Rk = proposal.rotations[k]
        for _ in range(3):
            Rk = Rk @ _so3_exp(wk @ so3_log(np.einsum("ji,njk->nik", Rk, R), check=False))
        tk = wk @ t
        x = np.concatenate([so3_log(np.einsum("ji,njk->nik", Rk, R), check=False), t - tk], axis=1)
        C = (x * wk[:, None]).T @ x / max(1.0 - np.sum(wk**2), 1e-12) + floor
        if alpha < 1.0:
            # The draws were weighted by target^a q^(1-a): for Gaussians its precision is
            # a P_target + (1 - a) P_q, so undo the proposal's share. Variances are capped at
            # 25x the flattened estimate's largest.
            Pa = np.linalg.inv(C)
            P = (Pa - (1.0 - alpha) * np.linalg.inv(proposal.covariances[k])) / alpha
            lam, V = np.linalg.eigh(0.5 * (P + P.T))
            lam = np.maximum(lam, np.linalg.eigvalsh(Pa).min() / 25.0)
            C = (V / lam) @ V.T
        C = _bounded(C, proposal.covariances[k], p)
        Rs.append(Rk)
        ts.append(tk)
        Cs.append(0.5 * (C + C.T))
        ws.append(mixed)
    if not ws:
        return None
    ws_a = np.asarray(ws) / np.sum(ws)
    ws_a = np.maximum(ws_a, p.min_component_weight / len(ws_a))
    return TangentMixture(np.stack(Rs), np.stack(ts), np.stack(Cs), ws_a / ws_a.sum(), proposal.dof)


def _sweep(log_target: LogTarget, adapted: TangentMixture, temp: float, best: float,
           p: ISParams) -> tuple[tuple[NDArray, NDArray, NDArray, NDArray] | None, int]:
    """New components on the good, uncovered turns of the adapted components' flat directions.

    Components are taken heaviest first, per basin (``ISParams.sweep_basins``): up to
    ``sweep_components`` in the basin of the heaviest, one in each basin whose centre no circle
    swept so far passes near (its axis from the Laplace fit at its centre), each basin with a
    budget of ``sweep_max_new`` new components.

    For a component ``(R_k, t_k, C_k)`` whose widest rotational direction ``u`` (object frame)
    has a standard deviation of at least ``sweep_min_sd``, the regression of the translation on
    the angle along ``u``, ``s = C_tr u / (u' C_rr u)`` (scene frame), is the velocity of a turn
    about the axis ``u`` through the object point ``c``: ``s = R_k (c x u)``, so
    ``c = u x (R_k' s)`` (the part of ``c`` across ``u``, all that a turn depends on). The turns
    ``R = R_k exp(phi [u]_x)``, ``t = t_k + R_k (c - exp(phi [u]_x) c)`` on a grid of ``phi``
    over the whole circle are scored on the target; those within ``sweep_window`` (tempered)
    nats of the best value seen and outside 2 standard deviations (chart metric) of every
    component get new components, best first: ``C_k`` with its spread along ``u`` set to
    ``sweep_spacing`` (so the next one sits about three spacings further on).

    Returns
    -------
    components : (R (m, 3, 3), t (m, 3), C (m, 6, 6), w (m,)) or None
        The new components; ``w`` is their parent's weight times ``exp`` of their value's
        shortfall from the parent's centre, at least 1/10 of it.
    num_evaluations : int
    """
    phi = np.radians(np.arange(0.0, 360.0, float(p.sweep_step)))
    spacing = math.radians(float(p.sweep_spacing))
    Rs: list[NDArray] = []
    ts: list[NDArray] = []
    Cs: list[NDArray] = []
    ws: list[float] = []
    n_eval = 0
    comps = list(zip(adapted.rotations, adapted.translations, adapted._chol, strict=True))  # noqa: SLF001

    def near(Rj: NDArray, tj: NDArray, Lj: NDArray, T: NDArray) -> NDArray:
        """(n,) whether the poses ``T`` lie within 2 standard deviations of a component."""
        x = np.concatenate([so3_log(np.einsum("ji,njk->nik", Rj, T[:, :3, :3]), check=False),
                            T[:, :3, 3] - tj], axis=1)
        return np.sum(np.linalg.solve(Lj, x.T) ** 2, axis=0) <= 4.0

    # The heaviest components with a flat direction, per basin: one of them may carry a poor
    # estimate of the axis (a short arc seen), and the sweep is cheap next to a round. A light
    # component off every swept circle (the demo's mug upside down, a ring of its own) gets too
    # few pilot draws to widen along its ring, so it is swept too, with a budget of its own.
    rot_tol, trans_tol = 2.0 * spacing, 2.0 * float(p.max_translation_noise)
    circles: list[list[NDArray]] = []  # per basin: the turns of its sweeps
    swept: list[int] = []  # per basin: components swept
    added: list[int] = []  # per basin: components placed
    for k in np.argsort(-adapted.weights):
        C = adapted.covariances[k]
        lam, V = np.linalg.eigh(C[:3, :3])
        if math.sqrt(lam[-1]) < math.radians(float(p.sweep_min_sd)):
            continue  # no flat rotational direction
        Rk, tk = adapted.rotations[k], adapted.translations[k]
        b = _basin_of(Rk, tk, circles, rot_tol, trans_tol)
        if b < 0:
            if not circles or len(circles) < int(p.sweep_basins):
                circles.append([])
                swept.append(0)
                added.append(0)
                b = len(circles) - 1
            else:
                b = 0  # beyond sweep_basins: counted with the heaviest basin
        # The heaviest basin's axis estimate may be poor (several sweeps); another basin gets
        # one sweep: each sweep's circle lies a little off the others', and the components it
        # leaves off the circle before add up (the mixture's density costs per component).
        if swept[b] >= (p.sweep_components if b == 0 else 1) or added[b] >= p.sweep_max_new:
            continue
        swept[b] += 1
        if b > 0:
            # A light component's refits rest on a dozen effective draws (or none): its axis
            # can be off by tens of degrees and millimetres. The Laplace fit at its centre gives
            # the ridge's own direction (73 evaluations).
            T_k = np.eye(4)
            T_k[:3, :3], T_k[:3, 3] = Rk, tk
            C = _laplace_covariances(_laplace_precisions(log_target, T_k[None], temp, p), p)[0]
            n_eval += len(_stencil())
            lam, V = np.linalg.eigh(C[:3, :3])
            if math.sqrt(lam[-1]) < math.radians(float(p.sweep_min_sd)):
                continue
        u = V[:, -1]
        c = np.cross(u, Rk.T @ (C[3:, :3] @ u / lam[-1]))
        E = _so3_exp(phi[:, None] * u)
        T = np.tile(np.eye(4), (len(phi), 1, 1))
        T[:, :3, :3] = Rk @ E
        T[:, :3, 3] = tk + (c - E @ c) @ Rk.T
        circles[b].append(T)
        f = np.asarray(log_target(T), dtype=np.float64).reshape(-1) / temp
        n_eval += len(phi)
        f = np.where(np.isfinite(f), f, -np.inf)
        thresh = max(best, float(f.max())) - float(p.sweep_window)
        uu = np.r_[u, np.zeros(3)]
        # C scaled along u (a congruence: stays positive definite).
        A = np.eye(6) + (spacing / math.sqrt(lam[-1]) - 1.0) * np.outer(uu, uu)
        Cn = A @ C @ A
        Cn = 0.5 * (Cn + Cn.T)
        Ln = np.linalg.cholesky(Cn)
        log.debug("sweep of component %d (basin %d, sd %.1f deg): best %.1f, %s", k, b,
                  math.degrees(math.sqrt(lam[-1])), float(f.max()) - best,
                  " ".join(f"{x - best:.0f}" for x in f[::3]))
        covered = np.zeros(len(phi), dtype=bool)
        for Rj, tj, Lj in comps:
            covered |= near(Rj, tj, Lj, T)
        for i in np.argsort(-f):
            if f[i] < thresh or added[b] >= p.sweep_max_new:
                break
            if covered[i]:
                continue
            Rs.append(T[i, :3, :3])
            ts.append(T[i, :3, 3])
            Cs.append(Cn)
            covered |= near(T[i, :3, :3], T[i, :3, 3], Ln, T)
            ws.append(float(adapted.weights[k]) * max(0.1, math.exp(min(float(f[i] - f[0]), 0.0))))
            added[b] += 1
    if not ws:
        return None, n_eval
    R_new, t_new, C_new, n_fit = _newton_fit(log_target, np.stack(Rs), np.stack(ts), np.stack(Cs), temp, p)
    return (R_new, t_new, C_new, np.asarray(ws)), n_eval + n_fit


def _basin_of(R: NDArray, t: NDArray, circles: list[list[NDArray]], rot_tol: float, trans_tol: float) -> int:
    """Index of the first basin one of whose swept circles (poses (m, 4, 4)) passes within
    ``rot_tol`` (rad) and ``trans_tol`` (m) of the pose ``(R, t)``; -1 if none does."""
    for b, turns in enumerate(circles):
        for T in turns:
            ang = np.linalg.norm(so3_log(np.einsum("ji,njk->nik", R, T[:, :3, :3]), check=False), axis=1)
            if np.any((ang <= rot_tol) & (np.linalg.norm(T[:, :3, 3] - t, axis=1) <= trans_tol)):
                return b
    return -1


def _newton_fit(log_target: LogTarget, R: NDArray, t: NDArray, C: NDArray, temp: float,
                p: ISParams) -> tuple[NDArray, NDArray, NDArray, int]:
    """Swept components moved onto the ridge they sit near: one Newton step on the
    finite-difference stencil of :func:`_laplace_precisions` (gradient and Hessian of the
    tempered target, step ``laplace_step`` noise units), restricted to the directions of downward
    curvature and at most 2 noise units long; the covariance across the swept direction is then
    the Laplace one (clipped and inflated as the seeds' are), along it the swept component's own.
    A turned pose is only as good as the axis it was turned about: off the ridge by a few
    millimetres, its component's draws miss the ridge and the few that hit it carry the weight."""
    st = _stencil()
    D = np.array([p.rotation_noise] * 3 + [p.translation_noise] * 3)
    h = float(p.laplace_step)
    x = st * D * h
    K = len(R)
    T = np.tile(np.eye(4), (K, len(st), 1, 1))
    T[:, :, :3, :3] = np.einsum("kij,njl->knil", R, _so3_exp(x[:, :3]))
    T[:, :, :3, 3] = t[:, None, :] + x[None, :, 3:]
    f = np.asarray(log_target(T.reshape(-1, 4, 4)), dtype=np.float64).reshape(K, len(st)) / temp
    f = np.where(np.isfinite(f), f, np.nanmin(np.where(np.isfinite(f), f, np.nan)) - 100.0) \
        if np.any(np.isfinite(f)) else np.zeros_like(f)
    P = _stencil_hessian(f, p)  # per noise unit squared
    g = (f[:, 1::2][:, :6] - f[:, 2::2][:, :6]) / (2.0 * h)  # per noise unit
    C_lap = _laplace_covariances(P, p)
    R_out, t_out, C_out = R.copy(), t.copy(), C.copy()
    for k in range(K):
        lam, V = np.linalg.eigh(0.5 * (P[k] + P[k].T))
        down = lam > 1e-6
        step = V[:, down] @ ((V[:, down].T @ g[k]) / lam[down])
        nrm = np.linalg.norm(step)
        if nrm > 2.0:
            step *= 2.0 / nrm
        dx = step * D
        R_out[k] = R[k] @ _so3_exp(dx[:3])
        t_out[k] = t[k] + dx[3:]
        # Along the swept direction (the old component's widest), keep its spread.
        lam_c, V_c = np.linalg.eigh(C[k][:3, :3])
        uu = np.r_[V_c[:, -1], np.zeros(3)]
        ratio = math.sqrt(lam_c[-1] / max(float(uu @ C_lap[k] @ uu), 1e-300))
        A = np.eye(6) + (ratio - 1.0) * np.outer(uu, uu)
        Ck = A @ C_lap[k] @ A
        C_out[k] = 0.5 * (Ck + Ck.T)
    return R_out, t_out, C_out, K * len(st)


def _births(log_target: LogTarget, mix: TangentMixture, logs: NDArray, R: NDArray, t: NDArray,
            w: NDArray, temp: float, p: ISParams) -> tuple[NDArray, NDArray, NDArray, NDArray] | None:
    """Components born at a round's heavy, stray draws: a draw holding more than ``birth_weight``
    of the round's weight and more than 3 standard deviations (chart metric) from the component
    most likely to have drawn it sits on a peak no component covers (a sweep's circle can miss
    a narrow one); it gets a component there, shaped as that one and fitted by
    :func:`_newton_fit`, weighted by the draw's share. At most two per round."""
    Rs, ts, Cs, ws = [], [], [], []
    for i in np.argsort(-w)[:2]:
        if w[i] <= p.birth_weight:
            break
        k = int(np.argmax(logs[:, i]))
        x = np.concatenate([so3_log(mix.rotations[k].T @ R[i], check=False), t[i] - mix.translations[k]])
        if np.sum((mix._chol_inv[k] @ x) ** 2) <= 9.0:  # noqa: SLF001
            continue
        Rs.append(R[i])
        ts.append(t[i])
        Cs.append(mix.covariances[k])
        ws.append(float(w[i]))
    if not ws:
        return None
    R_new, t_new, C_new, _ = _newton_fit(log_target, np.stack(Rs), np.stack(ts), np.stack(Cs), temp, p)
    return R_new, t_new, C_new, np.asarray(ws)


def _add_components(mix: TangentMixture, new: tuple[NDArray, NDArray, NDArray, NDArray],
                    share: float) -> TangentMixture:
    """``mix`` with the components ``new``, which get (together) at most ``share`` of the mass."""
    R, t, C, w = new
    w = np.asarray(w, dtype=np.float64)
    frac = min(share, float(w.sum()) / (float(w.sum()) + 1.0))
    return TangentMixture(np.concatenate([mix.rotations, R]), np.concatenate([mix.translations, t]),
                          np.concatenate([mix.covariances, C]),
                          np.concatenate([mix.weights * (1.0 - frac), frac * w / w.sum()]), mix.dof)


def importance_sample(
    log_target: LogTarget,
    seeds: ArrayLike,
    *,
    params: ISParams | None = None,
    rng: np.random.Generator | int | None = None,
    fixed_share: ArrayLike | None = None,
) -> ISResult:
    """Adaptive, noise-injected importance sampling of ``exp(log_target(T) / temperature)``.

    Parameters
    ----------
    log_target : callable
        ``log_target(T)`` with ``T`` (B, 4, 4) returns (B,) log-density values (up to a
        constant), e.g. a :class:`~certpose.model.likelihood.PoseLikelihood`. Its density is taken
        with respect to Haar measure x Lebesgue (the measure of :class:`TangentMixture`).
    seeds : (K, 4, 4) or (4, 4) array_like
        Poses the proposal starts around; a seed's initial mixture share follows the tempered
        target at it (``e^-10`` of the best's share 10 nats below), floored at 1%.
    params : ISParams, optional
        ``temperature`` None means 1 here.
    rng : numpy Generator, int or None
    fixed_share : (K,) array_like, optional
        Initial shares of some seeds, fixed (in (0, 1), together under 1), NaN for the seeds
        whose share follows the rule above (they share the rest), e.g. the half turns of
        :func:`sample_pose_distribution`.

    Returns
    -------
    ISResult
    """
    p = params or ISParams()
    gen = resolve_rng(rng)
    T0 = _check_seeds(seeds)
    temp = 1.0 if p.temperature is None else float(p.temperature)
    K = len(T0)
    t_start = time.perf_counter()  # the seeds' values and Laplace fits are part of the work
    # Seeds weighted by the target at the seed (a seed 10 nats worse starts with e^-10 the mass,
    # floored at 1% so that every seed keeps a chance).
    ls = np.asarray(log_target(T0), dtype=np.float64).reshape(-1) / temp
    ls = np.where(np.isfinite(ls), ls, -np.inf)
    sw = np.exp(ls - ls.max()) if np.any(np.isfinite(ls)) else np.ones(K)
    sw = np.maximum(sw / sw.sum(), 0.01)
    if fixed_share is not None:
        sw = _fixed_shares(ls, fixed_share)
    covs = np.repeat(_isotropic(p.rotation_noise, p.translation_noise)[None], K, 0)
    n_eval = K
    if p.laplace:
        covs = _laplace_covariances(_laplace_precisions(log_target, T0, temp, p), p)
        n_eval += K * len(_stencil())
    initial = TangentMixture(T0[:, :3, :3].copy(), T0[:, :3, 3].copy(), covs, sw / sw.sum(), p.dof)
    adapted, mix = initial, initial
    n_last = int(p.draws)
    n_pilot = int(p.pilot_draws) or max(n_last // 4, 500)
    ess_rounds: list[float] = []
    sweep_rounds = {int(r) for r in p.sweep_rounds}
    best, n_swept, n_born = float(np.max(ls)), 0, 0
    bar = _progress(int(p.rounds), "importance sampling", p.progress)
    try:
        for r in range(int(p.rounds)):
            n = n_last if r + 1 == p.rounds else n_pilot
            n_eval += n
            R, t = mix.sample(n, gen)
            T = np.tile(np.eye(4), (n, 1, 1))
            T[:, :3, :3], T[:, :3, 3] = R, t
            lt = np.asarray(log_target(T), dtype=np.float64).reshape(-1)
            if lt.shape != (n,):
                raise ValueError(f"Expected `log_target` to return shape ({n},), got {lt.shape}.")
            if np.any(np.isnan(lt)):
                raise ValueError("`log_target` returned NaN.")
            logs = mix.component_log_densities(R, t)
            logw = lt / temp - logsumexp(logs, axis=0)
            if not np.any(np.isfinite(logw)):
                raise ValueError("every draw has zero target density; check the seeds.")
            w = np.exp(logw - logw.max())
            w /= w.sum()
            ess = float(1.0 / np.sum(w**2))
            ess_rounds.append(ess)
            log.debug("IS round %d: ESS %.0f of %d, %d components", r, ess, n, len(mix.weights))
            bar.update(1)
            if r + 1 < p.rounds:
                wf, alpha = _flattened(logw, 0.2)
                new = _refit(mix, logs, len(adapted.weights), R, t, wf, alpha, p, w)
                adapted = new if new is not None else initial
                born = _births(log_target, mix, logs, R, t, w, temp, p)
                if born is not None:
                    n_eval += len(born[3]) * len(_stencil())
                    n_born += len(born[3])
                    log.debug("IS round %d: %d components born at heavy draws", r, len(born[3]))
                    adapted = _add_components(adapted, born, 0.5)
                    if p.sweep_defensive:
                        initial = _add_components(initial, born, 0.5)
                if r in sweep_rounds:
                    best = max(best, float(np.max(lt)) / temp)
                    found, n_sw = _sweep(log_target, adapted, temp, best, p)
                    n_eval += n_sw
                    if found is not None:
                        log.debug("IS round %d: the sweep adds %d components", r, len(found[3]))
                        n_swept += len(found[3])
                        adapted = _add_components(adapted, found, 0.5)
                        if p.sweep_defensive:
                            initial = _add_components(initial, found, 0.5)
                mix = _with_defensive(adapted, initial, p.defensive)
    finally:
        bar.close()
    keep = np.isfinite(logw)
    weighted = PoseDistribution.from_log_weights(R[keep], t[keep], logw[keep])
    dist = weighted.resample(int(p.resample), rng=gen) if p.resample else weighted
    seconds = time.perf_counter() - t_start
    status = "ok" if ess_rounds[-1] >= 0.01 * n else "low_ess"
    msg = (f"{p.rounds} rounds ({n_pilot} pilot draws, {n} final) at temperature {temp:.3g}: ESS {ess_rounds[-1]:.0f} "
           f"({', '.join(f'{e:.0f}' for e in ess_rounds)} per round), {n_swept} components from sweeps, {n_born} born, "
           f"{seconds:.2f} s")
    log.info("importance sampling: %s", msg)
    return ISResult(dist, weighted, mix, temp, tuple(ess_rounds), n_eval, seconds,
                    status, msg, lt[keep])


def _fixed_shares(ls: NDArray[np.float64], fixed: ArrayLike) -> NDArray[np.float64]:
    """Initial seed shares: ``fixed`` where it is a number, the rest of the mass shared by the
    others as :func:`importance_sample`'s rule gives it from the tempered values ``ls``."""
    fixed = np.asarray(fixed, dtype=np.float64).reshape(-1)
    given = np.isfinite(fixed)
    if fixed.shape != ls.shape or not np.all((fixed[given] > 0) & (fixed[given] < 1)) \
            or fixed[given].sum() >= 1 or np.all(given):
        raise ValueError(f"Expected `fixed_share` of shape {ls.shape}, in (0, 1) or NaN, the numbers summing "
                         f"to under 1 and at least one NaN, got {fixed}.")
    rest = ls[~given]
    sw = np.exp(rest - rest.max()) if np.any(np.isfinite(rest)) else np.ones(len(rest))
    sw = np.maximum(sw / sw.sum(), 0.01)
    out = fixed.copy()
    out[~given] = (1.0 - fixed[given].sum()) * sw / sw.sum()
    return out


def default_temperature(likelihood, T: ArrayLike, *, scale: float = 1.0,  # noqa: ANN001
                        correlation_voxels: float = 4.0) -> float:
    """The default temperature rule (see the module docstring): ``scale * N / n_eff``.

    ``N`` is the model's total point weight (its number of points unless it is area-weighted),
    ``n_eff`` the number of distinct cells of side ``correlation_voxels`` grid voxels that the
    model points of ``likelihood`` (a :class:`~certpose.model.likelihood.PoseLikelihood`)
    occupy at pose ``T`` (4, 4).
    """
    T = np.asarray(T, dtype=np.float64)
    pts = likelihood._points @ T[:3, :3].T + T[:3, 3]
    cell = likelihood.grid.voxel_size * float(correlation_voxels)
    n_eff = len(np.unique(np.floor((pts - likelihood.grid.origin) / cell).astype(np.int64), axis=0))
    return float(scale) * likelihood.total_weight / max(n_eff, 1)


def seeds_from_mle(mle) -> NDArray[np.float64]:  # noqa: ANN001
    """Seed poses from an :class:`~certpose.estimation.mle.MLEResult`: the MLE pose, the eq. (2)
    solution (GNC / certified), the refined hypotheses and the modes, near-duplicates removed."""
    poses = [np.asarray(mle.T_scene_object)]
    if mle.eq2_result is not None:
        poses.append(np.asarray(mle.eq2_result.T_target_source))
    poses += [np.asarray(m.T_scene_object) for m in mle.modes]
    poses += [np.asarray(h.pose) for h in mle.hypotheses]
    out: list[NDArray[np.float64]] = []
    for T in poses:
        if _is_new(T, out):
            out.append(T)
    return np.stack(out)


def principal_half_turns(likelihood, T: ArrayLike) -> NDArray[np.float64]:  # noqa: ANN001
    """(3, 4, 4) half turns of ``T`` (4, 4) about the principal axes of the model points of
    ``likelihood`` (a :class:`~certpose.model.likelihood.PoseLikelihood`) through their centroid:
    the object-frame map ``x -> F (x - c) + c`` composed with ``T`` (``T_scene_object``)."""
    T = np.asarray(T, dtype=np.float64)
    pts = likelihood._points
    c = pts.mean(axis=0)
    _, V = np.linalg.eigh(np.cov((pts - c).T))
    out = np.repeat(T[None], 3, axis=0)
    for i in range(3):
        F = _so3_exp(np.pi * V[:, i])
        out[i, :3, :3] = T[:3, :3] @ F
        out[i, :3, 3] = T[:3, :3] @ (c - F @ c) + T[:3, 3]
    return out


def half_turn_seeds(likelihood, T: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:  # noqa: ANN001
    """The half turns of ``T`` (:func:`principal_half_turns`), each refined on eq. (1) by
    :func:`certpose.estimation.batch.refine_poses` (the three climb in one batch; translation in
    units of the model's radius about its centroid). 0.05 s on the demo mug where
    :func:`~certpose.estimation.mle.refine_pose` one at a time (as
    :func:`~certpose.sampling.calibration.find_basins` does) takes 0.2 s.

    Returns
    -------
    poses : (3, 4, 4) ndarray
        Refined ``T_scene_object``.
    log_likelihood : (3,) ndarray
        Eq. (1) at each (nats, not tempered).
    """
    from certpose.estimation.batch import refine_poses

    pts = likelihood._points
    radius = float(np.linalg.norm(pts - pts.mean(axis=0), axis=1).max())
    P, v = refine_poses(likelihood, principal_half_turns(likelihood, T), scale=radius)
    return np.asarray(P, dtype=np.float64), np.asarray(v, dtype=np.float64)


def _is_new(T: NDArray[np.float64], others: NDArray[np.float64]) -> bool:
    """Whether ``T`` lies more than 2 mm or 0.02 rad from every pose of ``others``."""
    return all(np.linalg.norm(T[:3, 3] - S[:3, 3]) > 2e-3
               or np.linalg.norm(so3_log(S[:3, :3].T @ T[:3, :3], check=False)) > 0.02 for S in others)


def sample_pose_distribution(
    likelihood,  # noqa: ANN001 - a PoseLikelihood
    seeds: ArrayLike | Sequence[NDArray[np.float64]],
    *,
    params: ISParams | None = None,
    rng: np.random.Generator | int | None = None,
) -> ISResult:
    """Sample ``exp(eq. (1) / temperature)`` with :func:`importance_sample`.

    ``params.temperature`` None uses :func:`default_temperature` at the first seed. With
    ``params.half_turns`` the first seed's refined half turns (:func:`half_turn_seeds`) join the
    seeds (those within ``half_turn_window`` tempered nats of the best seed and not already
    among them), each with ``half_turn_share`` of the initial mixture; the time they take
    is added to :attr:`ISResult.seconds`. The particles are in the likelihood's scene frame
    (``T_scene_object``).
    """
    from dataclasses import replace

    p = params or ISParams()
    T0 = _check_seeds(np.asarray(seeds, dtype=np.float64))
    if p.temperature is None:
        p = replace(p, temperature=default_temperature(likelihood, T0[0], scale=p.temperature_scale,
                                                       correlation_voxels=p.correlation_voxels))
    if not p.half_turns:
        return importance_sample(likelihood.log_likelihood, T0, params=p, rng=rng)
    t_start = time.perf_counter()
    H, vH = half_turn_seeds(likelihood, T0[0])
    best = float(np.max(likelihood.log_likelihood(T0)))
    added = 0
    for T, v in zip(H, vH, strict=True):
        if np.isfinite(v) and (v - best) / p.temperature >= -p.half_turn_window and _is_new(T, T0):
            T0 = np.concatenate([T0, T[None]])
            added += 1
    log.debug("half turns: %s tempered nats from the best seed, %d added",
              " ".join(f"{(v - best) / p.temperature:.1f}" for v in vH), added)
    share = np.r_[np.full(len(T0) - added, np.nan), np.full(added, p.half_turn_share)]
    seconds = time.perf_counter() - t_start
    res = importance_sample(likelihood.log_likelihood, T0, params=p, rng=rng,
                            fixed_share=share if added else None)
    return replace(res, seconds=res.seconds + seconds,
                   message=f"{res.message} (+ {added} half-turn seeds, {seconds:.2f} s)")


def perturbed_eq2_seeds(
    eq2,  # noqa: ANN001 - an Eq2Problem
    num: int,
    *,
    scale: float = 1.0,
    rng: np.random.Generator | int | None = None,
) -> NDArray[np.float64]:
    """Perturb-and-MAP seeds: eq. (2) re-solved ``num`` times with perturbed weights ``c_ij``.

    Each solve adds centred Gumbel noise of scale ``scale`` (nats) to every ``c_ij`` (weights
    clipped at 0) and solves it as the pipeline does (``solvers.solve_registration(method="auto")``: max-clique pruning, then GNC-TLS). The
    solver takes no initial pose, so these are cold starts, not the issue's warm starts.

    Returns
    -------
    (num, 4, 4) ndarray
        ``T_scene_object`` of each re-solve.
    """
    from dataclasses import replace

    from solvers import solve_registration

    if int(num) < 0:
        raise ValueError(f"Expected `num` >= 0, got {num}.")
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"Expected `scale` to be positive and finite, got {scale}.")
    gen = resolve_rng(rng)
    out = np.empty((int(num), 4, 4))
    base = np.asarray(eq2.problem.weights, dtype=np.float64)
    for i in range(int(num)):
        noise = scale * (gen.gumbel(size=base.shape) - np.euler_gamma)
        prob = replace(eq2.problem, weights=np.maximum(base + noise, 0.0))
        out[i] = solve_registration(prob, method="auto").T_target_source
    return out
