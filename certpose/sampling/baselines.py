"""Baselines for the importance sampler, on the same target ``exp(log_target / temperature)``.

* :func:`de_sample`: two-point differential evolution (Nevergrad ``TwoPointsDE``), the paper's
  sampler. As its appendix describes, every pose the optimiser evaluates is kept, weighted by
  the unnormalised target and resampled. Those weights ignore how densely DE evaluated each
  region (the optimiser's sampling density is unknown), so the result approximates
  ``target x (density of evaluated poses)``, sharper than the target: a baseline, not an
  unbiased sampler. The raw log-weights are kept, so Pareto-k is reported as for ours.
* :func:`mcmc_sample`: random-walk Metropolis on SE(3), parallel chains, with a tangent-space
  proposal ``R' = R exp(w)``, ``t' = t + d``, ``(w, d) ~ N(0, s^2 S)`` (symmetric with respect to
  Haar x Lebesgue, the measure the target density is taken against). ``S`` and ``s`` are adapted
  during warm-up (within-chain covariance scaled by ``2.38^2 / 6``; ``log s`` driven towards the
  target acceptance rate) and then frozen; the post-warm-up states are the (equally weighted)
  particles. Its ESS is arviz's bulk ESS over the chains, the least over the six chart
  coordinates (not Kish's, which is meaningless for equal weights).

Both search in the chart of :mod:`certpose.sampling.chart` around a reference pose (the MLE), and
stop at the first of ``max_evaluations`` target evaluations and ``max_seconds`` of wall-clock, so
they can be run at the same budget as :func:`certpose.sampling.importance_sample`.
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from certpose.sampling.chart import check_pose, from_chart, to_chart
from certpose.sampling.distribution import PoseDistribution
from certpose.sampling.sampler import LogTarget, _check_seeds, _progress
from solvers.validation import resolve_rng

__all__ = ["DEParams", "MCMCParams", "SamplerResult", "de_sample", "mcmc_sample"]

log = logging.getLogger(__name__)


def _check_budget(max_evaluations: int, max_seconds: float | None) -> None:
    if int(max_evaluations) < 1:
        raise ValueError(f"Expected `max_evaluations` >= 1, got {max_evaluations}.")
    if max_seconds is not None and not (math.isfinite(max_seconds) and max_seconds > 0):
        raise ValueError(f"Expected `max_seconds` to be positive and finite or None, got {max_seconds}.")


def _check_positive(obj: Any, *names: str) -> None:
    for name in names:
        v = getattr(obj, name)
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"Expected `{name}` to be positive and finite, got {v}.")


@dataclass(frozen=True)
class DEParams:
    """Knobs of :func:`de_sample`.

    Attributes
    ----------
    max_evaluations : int
        Target evaluations (the optimiser's budget).
    max_seconds : float or None
        Wall-clock limit (s); the run stops at whichever limit comes first.
    batch : int
        Candidates per ask/evaluate/tell round (Nevergrad's ``num_workers``).
    rotation_bound : float
        Half-side of the search box of the chart's rotation vector (rad).
    translation_bound : float
        Half-side of the search box of the chart's translation (m).
    temperature : float
    resample : int
        Particles after resampling (0 = the weighted population).
    progress : bool
    """

    max_evaluations: int = 10_000
    max_seconds: float | None = None
    batch: int = 64
    rotation_bound: float = 1.0
    translation_bound: float = 0.02
    temperature: float = 1.0
    resample: int = 0
    progress: bool = False

    def __post_init__(self) -> None:
        _check_budget(self.max_evaluations, self.max_seconds)
        if int(self.batch) < 1:
            raise ValueError(f"Expected `batch` >= 1, got {self.batch}.")
        _check_positive(self, "rotation_bound", "translation_bound", "temperature")
        if int(self.resample) < 0:
            raise ValueError(f"Expected `resample` >= 0, got {self.resample}.")


@dataclass(frozen=True)
class MCMCParams:
    """Knobs of :func:`mcmc_sample`.

    Attributes
    ----------
    max_evaluations : int
        Target evaluations (``chains`` per step).
    max_seconds : float or None
        Wall-clock limit (s); the run stops at whichever limit comes first.
    chains : int
        Parallel chains (evaluated together).
    warmup : float
        Fraction of the budget (evaluations, or seconds when that limit is tighter) spent
        adapting; those states are discarded.
    rotation_step, translation_step : float
        Initial proposal standard deviations (rad, m).
    target_acceptance : float
    start_window : float
        Chains start only at the seeds whose tempered target is within this many nats of the
        best seed's (round robin); a chain started hundreds of nats below would spend the whole
        budget climbing.
    adapt_every : int
        Steps between covariance updates during warm-up.
    temperature : float
    resample : int
        Particles after resampling (0 = every post-warm-up state).
    progress : bool
    """

    max_evaluations: int = 10_000
    max_seconds: float | None = None
    chains: int = 32
    warmup: float = 0.5
    rotation_step: float = 0.02
    translation_step: float = 0.002
    target_acceptance: float = 0.234
    start_window: float = 20.0
    adapt_every: int = 10
    temperature: float = 1.0
    resample: int = 0
    progress: bool = False

    def __post_init__(self) -> None:
        _check_budget(self.max_evaluations, self.max_seconds)
        if int(self.chains) < 2:
            raise ValueError(f"Expected `chains` >= 2, got {self.chains}.")
        if not 0.0 <= self.warmup < 1.0:
            raise ValueError(f"Expected `warmup` in [0, 1), got {self.warmup}.")
        if not 0.0 < self.target_acceptance < 1.0:
            raise ValueError(f"Expected `target_acceptance` in (0, 1), got {self.target_acceptance}.")
        if int(self.adapt_every) < 1:
            raise ValueError(f"Expected `adapt_every` >= 1, got {self.adapt_every}.")
        _check_positive(self, "rotation_step", "translation_step", "temperature", "start_window")
        if int(self.resample) < 0:
            raise ValueError(f"Expected `resample` >= 0, got {self.resample}.")


@dataclass(frozen=True, eq=False)
class SamplerResult:
    """Output of :func:`de_sample` and :func:`mcmc_sample`.

    Attributes
    ----------
    distribution : PoseDistribution
        The particles (resampled when ``resample`` > 0).
    weighted : PoseDistribution
        Before resampling (DE: raw log-weights kept; MCMC: equal weights).
    method : str
        ``"de"`` or ``"mcmc"``.
    temperature : float
    ess : float
        DE: Kish ESS of the weights. MCMC: arviz bulk ESS, least over the chart coordinates.
    num_evaluations : int
    seconds : float
    status : str
        ``"ok"``, ``"low_ess"`` (ESS below 1% of the particles, or below 10) or ``"too_short"``
        (MCMC: no state after warm-up).
    message : str
    info : dict
        Method details (MCMC: acceptance rate, final step scale, R-hat).
    """

    distribution: PoseDistribution
    weighted: PoseDistribution
    method: str
    temperature: float
    ess: float
    num_evaluations: int
    seconds: float
    status: str
    message: str
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def success(self) -> bool:
        return self.status == "ok"


def _eval(log_target: LogTarget, T: NDArray[np.float64]) -> NDArray[np.float64]:
    v = np.asarray(log_target(T), dtype=np.float64).reshape(-1)
    if v.shape != (len(T),):
        raise ValueError(f"Expected `log_target` to return shape ({len(T)},), got {v.shape}.")
    if np.any(np.isnan(v)):
        raise ValueError("`log_target` returned NaN.")
    return v


def _check_init(init: ArrayLike | None) -> NDArray[np.float64] | None:
    if init is None:
        return None
    x = np.asarray(init, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 6 or len(x) == 0:
        raise ValueError(f"Expected `init` to have shape (m, 6) with m >= 1, got {x.shape}.")
    if not np.all(np.isfinite(x)):
        raise ValueError("`init` contains NaN or infinite values.")
    return x


def de_sample(
    log_target: LogTarget,
    T_ref: ArrayLike,
    *,
    params: DEParams | None = None,
    init: ArrayLike | None = None,
    rng: np.random.Generator | int | None = None,
) -> SamplerResult:
    """The paper's sampler: Nevergrad ``TwoPointsDE`` on the chart around ``T_ref``, every
    evaluated pose importance-weighted by the target and resampled.

    Parameters
    ----------
    log_target : callable
        ``log_target(T)`` with ``T`` (B, 4, 4) returns (B,) values, e.g. a
        :class:`~certpose.model.likelihood.PoseLikelihood`.
    T_ref : (4, 4) array_like
        Centre of the search box (the MLE).
    params : DEParams, optional
    init : (m, 6) array_like, optional
        Chart coordinates suggested to the optimiser first (e.g.
        :func:`certpose.sampling.initialisers.nevergrad_population`); clipped to the box.
    rng : numpy Generator, int or None
        Seeds Nevergrad.

    Returns
    -------
    SamplerResult
    """
    import nevergrad as ng

    p = params or DEParams()
    T_ref = check_pose(T_ref)
    x0 = _check_init(init)
    gen = resolve_rng(rng)
    scale = np.array([p.rotation_bound] * 3 + [p.translation_bound] * 3)
    param = ng.p.Array(shape=(6,), lower=-1.0, upper=1.0)
    param.random_state = np.random.RandomState(int(gen.integers(2**31 - 1)))
    budget = int(p.max_evaluations)
    opt = ng.optimizers.TwoPointsDE(parametrization=param, budget=budget, num_workers=int(p.batch))
    if x0 is not None:
        for x in np.clip(x0 / scale, -1.0, 1.0):
            opt.suggest(x)
    xs: list[NDArray[np.float64]] = []
    vals: list[NDArray[np.float64]] = []
    done = 0
    t0 = time.perf_counter()
    bar = _progress(budget, "differential evolution", p.progress)
    try:
        while done < budget:
            if p.max_seconds is not None and time.perf_counter() - t0 >= p.max_seconds:
                break
            cands = [opt.ask() for _ in range(min(int(p.batch), budget - done))]
            x = np.stack([np.asarray(c.value, dtype=np.float64) for c in cands]) * scale
            v = _eval(log_target, from_chart(x, T_ref))
            for c, vi in zip(cands, v, strict=True):
                # Nevergrad wants finite losses; -inf targets become a large finite loss.
                opt.tell(c, float(-vi / p.temperature) if np.isfinite(vi) else 1e300)
            xs.append(x)
            vals.append(v)
            done += len(cands)
            bar.update(len(cands))
    finally:
        bar.close()
    seconds = time.perf_counter() - t0
    x = np.concatenate(xs)
    lw = np.concatenate(vals) / p.temperature
    keep = np.isfinite(lw)
    if not np.any(keep):
        raise ValueError("every evaluated pose has zero target density; check `T_ref` and the bounds.")
    T = from_chart(x[keep], T_ref)
    weighted = PoseDistribution.from_log_weights(T[:, :3, :3], T[:, :3, 3], lw[keep])
    dist = weighted.resample(int(p.resample), rng=gen) if p.resample else weighted
    ess = weighted.ess
    status = "ok" if ess >= max(10.0, 0.01 * len(weighted)) else "low_ess"
    msg = (f"TwoPointsDE: {done} evaluations in {seconds:.2f} s at temperature {p.temperature:.3g}, "
           f"population weighted by the target: ESS {ess:.0f} of {len(weighted)}")
    log.info("DE baseline: %s", msg)
    return SamplerResult(dist, weighted, "de", float(p.temperature), float(ess), done, seconds,
                         status, msg, {"best_log_target": float(lw.max() * p.temperature)})


def _chain_ess(x: NDArray[np.float64]) -> tuple[float, float]:
    """Least bulk ESS and largest R-hat over the coordinates of ``x`` (chains, draws, d)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import arviz

        ess = [float(arviz.ess(np.ascontiguousarray(x[:, :, j]), method="bulk"))
               for j in range(x.shape[2])]
        rhat = [float(arviz.rhat(np.ascontiguousarray(x[:, :, j]))) for j in range(x.shape[2])]
    ess_v = np.nan_to_num(np.asarray(ess), nan=0.0)
    return float(ess_v.min()), float(np.nanmax(rhat)) if np.any(np.isfinite(rhat)) else math.nan


def mcmc_sample(
    log_target: LogTarget,
    seeds: ArrayLike,
    *,
    params: MCMCParams | None = None,
    rng: np.random.Generator | int | None = None,
) -> SamplerResult:
    """Random-walk Metropolis on SE(3) with an adapted tangent-space proposal (module docstring).

    Parameters
    ----------
    log_target : callable
        ``log_target(T)`` with ``T`` (B, 4, 4) returns (B,) values.
    seeds : (K, 4, 4) or (4, 4) array_like
        Starting poses (e.g. the MLE's seeds, or draws of
        :func:`certpose.sampling.initialisers.initial_poses`); the chains start round robin at
        those within ``params.start_window`` nats of the best. The first seed is the chart's
        reference for the ESS.
    params : MCMCParams, optional
    rng : numpy Generator, int or None

    Returns
    -------
    SamplerResult
    """
    p = params or MCMCParams()
    S0 = _check_seeds(seeds)
    gen = resolve_rng(rng)
    C, temp = int(p.chains), float(p.temperature)
    t0 = time.perf_counter()
    ls = _eval(log_target, S0) / temp
    if not np.any(np.isfinite(ls)):
        raise ValueError("every seed has zero target density; check the seeds.")
    starts = S0[np.flatnonzero(ls >= ls.max() - p.start_window)]
    T = starts[np.arange(C) % len(starts)].copy()
    lp = _eval(log_target, T) / temp
    n_eval = len(S0) + C
    budget = int(p.max_evaluations)
    cov = np.diag([p.rotation_step**2] * 3 + [p.translation_step**2] * 3)
    log_s = 0.0
    L = np.linalg.cholesky(cov)
    warm_evals = p.warmup * budget
    warm_secs = None if p.max_seconds is None else p.warmup * p.max_seconds
    hist: list[NDArray[np.float64]] = []  # warm-up window (steps, C, 4, 4)
    kept_R: list[NDArray[np.float64]] = []
    kept_t: list[NDArray[np.float64]] = []
    accepted = np.zeros(2)  # (accepted, proposed) after warm-up
    step = 0
    warm = p.warmup > 0
    bar = _progress(budget, "random-walk Metropolis", p.progress)
    try:
        while n_eval + C <= budget:
            elapsed = time.perf_counter() - t0
            if p.max_seconds is not None and elapsed >= p.max_seconds:
                break
            if warm and (n_eval >= warm_evals or (warm_secs is not None and elapsed >= warm_secs)):
                warm = False
            x = math.exp(log_s) * gen.standard_normal((C, 6)) @ L.T
            Tp = T.copy()
            Tp[:, :3, :3] = np.einsum("nij,njk->nik", T[:, :3, :3], Rotation.from_rotvec(x[:, :3]).as_matrix())
            Tp[:, :3, 3] += x[:, 3:]
            lpp = _eval(log_target, Tp) / temp
            n_eval += C
            bar.update(C)
            with np.errstate(invalid="ignore"):
                acc = np.log(gen.random(C)) < lpp - lp
            T[acc], lp[acc] = Tp[acc], lpp[acc]
            step += 1
            if warm:
                log_s += (acc.mean() - p.target_acceptance) / math.sqrt(step)
                hist.append(T.copy())
                if step % int(p.adapt_every) == 0 and len(hist) >= 10:
                    H = np.stack(hist[-200:], axis=1)  # (C, steps, 4, 4)
                    # Within-chain spread, each chain in the chart around its own current state.
                    X = np.concatenate([to_chart(H[c, :, :3, :3], H[c, :, :3, 3], H[c, -1])
                                        for c in range(C)])
                    X = X.reshape(C, -1, 6) - X.reshape(C, -1, 6).mean(axis=1, keepdims=True)
                    emp = np.einsum("csi,csj->ij", X, X) / max(X.shape[0] * X.shape[1] - C, 1)
                    floor = np.diag([1e-4**2] * 3 + [1e-5**2] * 3)
                    cov = 2.38**2 / 6 * emp + floor
                    L = np.linalg.cholesky(cov)
                    log_s = 0.0
            else:
                kept_R.append(T[:, :3, :3].copy())
                kept_t.append(T[:, :3, 3].copy())
                accepted += (acc.sum(), C)
    finally:
        bar.close()
    seconds = time.perf_counter() - t0
    if not kept_R:
        # The budget ended during warm-up: the current states are all there is.
        kept_R, kept_t, status = [T[:, :3, :3]], [T[:, :3, 3]], "too_short"
    else:
        status = "ok"
    Rk = np.stack(kept_R, axis=1)  # (C, draws, 3, 3)
    tk = np.stack(kept_t, axis=1)
    n = Rk.shape[0] * Rk.shape[1]
    weighted = PoseDistribution(Rk.reshape(-1, 3, 3), tk.reshape(-1, 3), np.full(n, 1.0 / n))
    X = to_chart(Rk.reshape(-1, 3, 3), tk.reshape(-1, 3), S0[0]).reshape(C, -1, 6)
    ess, rhat = _chain_ess(X) if X.shape[1] >= 4 else (0.0, math.nan)
    if status == "ok" and ess < max(10.0, 0.01 * n):
        status = "low_ess"
    rate = float(accepted[0] / accepted[1]) if accepted[1] else math.nan
    dist = weighted.resample(int(p.resample), rng=gen) if p.resample else weighted
    msg = (f"random-walk Metropolis: {C} chains x {Rk.shape[1]} kept steps, {n_eval} evaluations in "
           f"{seconds:.2f} s at temperature {temp:.3g}; acceptance {rate:.2f}, bulk ESS {ess:.0f}, "
           f"R-hat {rhat:.2f}")
    log.info("MCMC baseline: %s", msg)
    return SamplerResult(dist, weighted, "mcmc", temp, ess, n_eval, seconds, status, msg,
                         {"acceptance": rate, "rhat": rhat, "step_scale": math.exp(log_s),
                          "proposal_covariance": cov})
