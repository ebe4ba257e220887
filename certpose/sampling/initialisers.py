"""Start other samplers from an MLE or a :class:`~certpose.sampling.PoseDistribution`.

Every initialiser speaks the one chart of :mod:`certpose.sampling.chart`: around a reference
pose ``T_ref``, ``xi = (log(R_ref^T R), t - t_ref)`` (6,), rotation vector in radians then
translation in metres. Write your model in ``xi`` and map back with
:func:`certpose.sampling.chart.from_chart`.

``T_ref`` defaults to the mean pose of the heaviest mode of a distribution, or to the pose
itself for an MLE. A single pose has no spread: its initial values are drawn around it from an
isotropic Gaussian (``rotation_sigma`` rad, ``translation_sigma`` m). From a distribution they
are resampled particles plus a jitter of a tenth of the distribution's standard deviations
(``N(0, 0.01 C)``), so they are distinct even where resampling repeats a
particle (emcee refuses linearly dependent walkers).

* Nevergrad: :func:`nevergrad_parametrization` (a bounded ``ng.p.Array`` whose ``init`` and
  ``sigma`` come from the source) and :func:`nevergrad_population` (points to ``suggest``).
* emcee: :func:`emcee_walkers` (``nwalkers`` x 6 for ``EnsembleSampler.run_mcmc``).
* PyMC: :func:`pymc_initvals` (one ``{name: xi}`` dict per chain for ``pm.sample(initvals=)``).
* gtsam: :func:`gtsam_priors` (per mode, a ``PriorFactorPose3`` on the mode's mean with its 6x6
  covariance converted to gtsam's tangent: rotation first, then translation, both in the body
  frame, i.e. ``(w, R_mean^T (t - t_mean))`` to first order).

All these libraries are optional (``pip install certpose[samplers]``); each is imported only
by the function that needs it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from certpose.sampling.chart import check_pose, from_chart, to_chart
from certpose.sampling.distribution import PoseDistribution
from solvers.validation import resolve_rng

__all__ = ["emcee_walkers", "gtsam_priors", "initial_chart_points", "initial_poses",
           "nevergrad_parametrization", "nevergrad_population", "pymc_initvals", "reference_pose"]

_DEFAULT_ROT, _DEFAULT_TRANS = 0.03, 0.003  # rad, m: the importance sampler's initial noise


def _as_source(source: Any) -> PoseDistribution | NDArray[np.float64]:
    """A PoseDistribution, or one (4, 4) pose (array, PoseResult, MLEResult)."""
    if isinstance(source, PoseDistribution):
        return source
    for attr in ("T_camera_object", "T_scene_object"):
        if hasattr(source, attr):
            return check_pose(getattr(source, attr), name=f"source.{attr}")
    return check_pose(source, name="source")


def _check_sigma(rotation_sigma: float, translation_sigma: float) -> None:
    for name, v in (("rotation_sigma", rotation_sigma), ("translation_sigma", translation_sigma)):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"Expected `{name}` to be positive and finite, got {v}.")


def reference_pose(source: Any) -> NDArray[np.float64]:
    """(4, 4) default chart reference: the heaviest mode's mean, or the pose itself."""
    s = _as_source(source)
    if isinstance(s, PoseDistribution):
        return s.modes()[0].T
    return s


def _spread(s: PoseDistribution | NDArray[np.float64], T_ref: NDArray[np.float64],
            rotation_sigma: float, translation_sigma: float) -> tuple[NDArray, NDArray]:
    """Chart mean (6,) and covariance (6, 6) of the source around ``T_ref``."""
    if isinstance(s, PoseDistribution):
        x = to_chart(s.rotations, s.translations, T_ref)
        m = s.weights @ x
        return m, np.einsum("n,ni,nj->ij", s.weights, x - m, x - m)
    return to_chart(s[:3, :3][None], s[:3, 3][None], T_ref)[0], \
        np.diag([rotation_sigma**2] * 3 + [translation_sigma**2] * 3)


def initial_chart_points(
    source: Any,
    n: int,
    *,
    T_ref: ArrayLike | None = None,
    rotation_sigma: float = _DEFAULT_ROT,
    translation_sigma: float = _DEFAULT_TRANS,
    rng: np.random.Generator | int | None = None,
) -> NDArray[np.float64]:
    """(n, 6) distinct chart points drawn from ``source`` (module docstring).

    Parameters
    ----------
    source : PoseDistribution, (4, 4) array_like, PoseResult or MLEResult
    n : int
    T_ref : (4, 4) array_like, optional
        Chart reference (default :func:`reference_pose`).
    rotation_sigma, translation_sigma : float
        Spread around a single pose (rad, m); unused for a distribution.
    rng : numpy Generator, int or None
    """
    if int(n) < 1:
        raise ValueError(f"Expected `n` >= 1, got {n}.")
    _check_sigma(rotation_sigma, translation_sigma)
    s = _as_source(source)
    T0 = reference_pose(s) if T_ref is None else check_pose(T_ref)
    gen = resolve_rng(rng)
    if not isinstance(s, PoseDistribution):
        m, C = _spread(s, T0, rotation_sigma, translation_sigma)
        return m + gen.standard_normal((int(n), 6)) * np.sqrt(np.diag(C))
    r = s.resample(int(n), rng=gen)
    x = to_chart(r.rotations, r.translations, T0)
    # Jitter of a tenth of the spread (inflates the variance by 1%), with a floor so that a
    # distribution collapsed onto one particle still gives distinct points.
    _, C = _spread(s, T0, rotation_sigma, translation_sigma)
    C = 0.01 * C + np.diag([1e-6] * 3 + [1e-7] * 3)
    L = np.linalg.cholesky(0.5 * (C + C.T))
    return x + gen.standard_normal(x.shape) @ L.T


def initial_poses(source: Any, n: int, *, rng: np.random.Generator | int | None = None,
                  **kwargs: Any) -> NDArray[np.float64]:
    """(n, 4, 4) poses of :func:`initial_chart_points` (e.g. chain starts for
    :func:`certpose.sampling.baselines.mcmc_sample`)."""
    s = _as_source(source)
    T0 = reference_pose(s) if kwargs.get("T_ref") is None else check_pose(kwargs["T_ref"])
    kwargs["T_ref"] = T0
    return from_chart(initial_chart_points(s, n, rng=rng, **kwargs), T0)


def nevergrad_parametrization(
    source: Any,
    *,
    T_ref: ArrayLike | None = None,
    rotation_bound: float = 1.0,
    translation_bound: float = 0.02,
    rotation_sigma: float = _DEFAULT_ROT,
    translation_sigma: float = _DEFAULT_TRANS,
) -> Any:
    """A Nevergrad ``Array`` of the chart, ``init`` at the source's chart mean, ``sigma`` its
    standard deviations, bounded by ``+-rotation_bound`` (rad) and ``+-translation_bound`` (m)."""
    import nevergrad as ng

    _check_sigma(rotation_sigma, translation_sigma)
    for name, v in (("rotation_bound", rotation_bound), ("translation_bound", translation_bound)):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"Expected `{name}` to be positive and finite, got {v}.")
    s = _as_source(source)
    T0 = reference_pose(s) if T_ref is None else check_pose(T_ref)
    m, C = _spread(s, T0, rotation_sigma, translation_sigma)
    bound = np.array([rotation_bound] * 3 + [translation_bound] * 3)
    init = np.clip(m, -0.999 * bound, 0.999 * bound)
    sigma = np.maximum(np.sqrt(np.diag(C)), 1e-6 * bound)
    return ng.p.Array(init=init, lower=-bound, upper=bound).set_mutation(sigma=sigma)


def nevergrad_population(source: Any, n: int, *, T_ref: ArrayLike | None = None,
                         rotation_bound: float = 1.0, translation_bound: float = 0.02,
                         rng: np.random.Generator | int | None = None,
                         **kwargs: Any) -> NDArray[np.float64]:
    """(n, 6) chart points inside the bounds of :func:`nevergrad_parametrization`, to pass to
    ``optimizer.suggest(x)`` before the first ``ask`` (or ``init=`` of
    :func:`certpose.sampling.baselines.de_sample`, which scales by the bounds itself)."""
    x = initial_chart_points(source, n, T_ref=T_ref, rng=rng, **kwargs)
    bound = np.array([rotation_bound] * 3 + [translation_bound] * 3)
    return np.clip(x, -0.999 * bound, 0.999 * bound)


def emcee_walkers(source: Any, nwalkers: int, *, rng: np.random.Generator | int | None = None,
                  **kwargs: Any) -> NDArray[np.float64]:
    """(nwalkers, 6) distinct, linearly independent initial walkers for
    ``emcee.EnsembleSampler(nwalkers, 6, log_prob)`` in the chart (needs ``nwalkers >= 12``)."""
    if int(nwalkers) < 12:
        raise ValueError(f"Expected `nwalkers` >= 12 (emcee needs twice the 6 dimensions), got {nwalkers}.")
    x = initial_chart_points(source, int(nwalkers), rng=rng, **kwargs)
    # emcee's check: the walkers' centred matrix must have full rank 6.
    if np.linalg.matrix_rank(x - x.mean(axis=0)) < 6:
        raise ValueError("the initial walkers are linearly dependent; the source has no spread.")
    return x


def pymc_initvals(source: Any, chains: int, *, name: str = "xi",
                  rng: np.random.Generator | int | None = None, **kwargs: Any) -> list[dict[str, NDArray]]:
    """One ``{name: xi}`` dict per chain, for ``pm.sample(chains=chains, initvals=...)`` on a model
    whose 6-vector random variable ``name`` is the chart coordinate."""
    if int(chains) < 1:
        raise ValueError(f"Expected `chains` >= 1, got {chains}.")
    x = initial_chart_points(source, int(chains), rng=rng, **kwargs)
    return [{name: row.copy()} for row in x]


def gtsam_priors(
    source: Any,
    key: int,
    *,
    max_modes: int = 5,
    min_mass: float = 0.0,
    rotation_sigma: float = _DEFAULT_ROT,
    translation_sigma: float = _DEFAULT_TRANS,
    min_sigma: float = 1e-6,
) -> list[tuple[Any, float]]:
    """Per mode, a ``gtsam.PriorFactorPose3`` on the mode's mean and its mass, heaviest first.

    The mode's chart covariance ``C`` (rotation vector, then ``t - t_mean`` in the parent frame)
    becomes gtsam's ``J C J^T`` with ``J = blockdiag(I, R_mean^T)`` (gtsam's Pose3 tangent is
    rotation then translation, both in the body frame); standard deviations below ``min_sigma``
    are raised to it so that the noise model is well conditioned.

    Parameters
    ----------
    source : PoseDistribution, (4, 4) array_like, PoseResult or MLEResult
        A single pose gives one factor with the isotropic ``rotation_sigma``/``translation_sigma``.
    key : int
        gtsam key of the pose variable (e.g. ``gtsam.symbol("x", 0)``).
    max_modes : int
    min_mass : float
        Modes lighter than this are skipped.
    """
    import gtsam

    _check_sigma(rotation_sigma, translation_sigma)
    if int(max_modes) < 1:
        raise ValueError(f"Expected `max_modes` >= 1, got {max_modes}.")
    s = _as_source(source)
    if isinstance(s, PoseDistribution):
        modes = [(m.rotation, m.translation, m.covariance, m.mass) for m in s.modes()]
    else:
        modes = [(s[:3, :3], s[:3, 3], np.diag([rotation_sigma**2] * 3 + [translation_sigma**2] * 3),
                  1.0)]
    out = []
    for R, t, C, mass in modes[: int(max_modes)]:
        if mass < min_mass:
            continue
        J = np.zeros((6, 6))
        J[:3, :3], J[3:, 3:] = np.eye(3), R.T
        G = J @ C @ J.T
        G = 0.5 * (G + G.T) + min_sigma**2 * np.eye(6)
        noise = gtsam.noiseModel.Gaussian.Covariance(G)
        pose = gtsam.Pose3(gtsam.Rot3(np.asarray(R)), gtsam.Point3(*np.asarray(t, dtype=float)))
        out.append((gtsam.PriorFactorPose3(int(key), pose, noise), float(mass)))
    return out
