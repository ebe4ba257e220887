r"""The pose distribution's target as a public callable, for other samplers.

certpose's samplers draw object poses from

.. math:: \pi(T) \propto \exp(\ell(T) / \tau),

with :math:`\ell` eq. (1) of the paper (the object's log-likelihood at pose ``T`` over the fused
scene field, :class:`~certpose.model.likelihood.PoseLikelihood`) and :math:`\tau` the
temperature the run used (``PoseResult.sampling["temperature"]``, the rule of
:func:`~certpose.sampling.sampler.default_temperature` otherwise). :class:`PoseTarget` is that
density, up to its normalising constant, as a function of ``T_camera_object`` (the frame of
:class:`~certpose.estimation.pipeline.PoseResult` and of its distribution), and, for samplers
that work in a vector space (emcee, PyMC, Nevergrad), of the 6-vector chart of
:mod:`certpose.sampling.chart` around a reference pose.

:func:`pose_target` builds it from a :class:`~certpose.estimation.pipeline.PoseResult` (its scene
field, classifier and camera) and the object model the run used; :func:`demo_object_model`
rebuilds the object model of :func:`~certpose.estimation.pipeline.run_demo`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from certpose.sampling.chart import check_pose, from_chart

__all__ = ["PoseTarget", "demo_object_model", "pose_target"]


def _as_poses(T: ArrayLike, name: str) -> tuple[NDArray[np.float64], bool]:
    T = np.asarray(T, dtype=np.float64)
    single = T.ndim == 2
    if T.shape[-2:] != (4, 4) or T.ndim not in (2, 3):
        raise ValueError(f"Expected `{name}` to have shape (4, 4) or (n, 4, 4), got {T.shape}.")
    return (T[None] if single else T), single


@dataclass(frozen=True, eq=False)
class PoseTarget:
    """The tempered pose log-density ``eq. (1) / temperature`` of one object in one frame.

    Parameters
    ----------
    likelihood : PoseLikelihood
        Eq. (1) of the scene, classifier and object model, evaluated on ``T_scene_object``.
    temperature : float
        :math:`\\tau > 0` (nats of eq. (1) per nat of the target).
    T_world_camera : (4, 4) ndarray
        The camera in the scene frame: ``T_scene_object = T_world_camera @ T_camera_object``.

    Notes
    -----
    Calls are vectorised: a batch of ``n`` poses costs one compiled pass (about 30 ns per model
    point and pose on one core: ``examples/benchmarks/bench_likelihood.py``).
    """

    likelihood: Any
    temperature: float
    T_world_camera: NDArray[np.float64]

    def __post_init__(self) -> None:
        if not (math.isfinite(self.temperature) and self.temperature > 0):
            raise ValueError(f"`temperature` must be positive and finite, got {self.temperature}.")
        object.__setattr__(self, "T_world_camera", check_pose(self.T_world_camera, name="T_world_camera"))

    def log_likelihood(self, T_camera_object: ArrayLike) -> float | NDArray[np.float64]:
        """Eq. (1) at ``T_camera_object`` (4, 4) or a batch (n, 4, 4), nats (float or (n,)).

        ``-inf`` where the object stands in observed free space (see
        :class:`~certpose.model.likelihood.LikelihoodParams`).
        """
        T, single = _as_poses(T_camera_object, "T_camera_object")
        values = np.atleast_1d(np.asarray(self.likelihood.log_likelihood(self.T_world_camera @ T),
                                          dtype=np.float64))
        return float(values[0]) if single else values

    def log_prob(self, T_camera_object: ArrayLike) -> float | NDArray[np.float64]:
        """``log_likelihood(T) / temperature``: the target's log-density up to a constant, per
        unit of the Haar measure on SO(3) times Lebesgue measure on translations (metres)."""
        return np.divide(self.log_likelihood(T_camera_object), self.temperature)

    __call__ = log_prob

    def chart_log_prob(self, xi: ArrayLike, T_ref: ArrayLike) -> float | NDArray[np.float64]:
        """The target's log-density per unit of the chart ``xi = (log(R_ref^T R), t - t_ref)``.

        For samplers in a vector space: the Haar measure's Jacobian of the exponential map,
        ``2 (1 - cos |w|) / |w|^2``, is added, so that the density integrates to the same
        probabilities in ``xi`` as on SE(3). Rotation vectors with ``|w| >= pi`` lie outside the
        one chart and get ``-inf``.

        Parameters
        ----------
        xi : (6,) or (n, 6) array_like
            Rotation vector (rad) then translation offset (m), see :mod:`certpose.sampling.chart`.
        T_ref : (4, 4) array_like
            The chart's centre, ``T_camera_object`` (e.g. the MLE or a mode's mean).

        Returns
        -------
        float or (n,) ndarray
        """
        x = np.asarray(xi, dtype=np.float64)
        single = x.ndim == 1
        x = np.atleast_2d(x)
        if x.shape[1] != 6 or x.ndim != 2:
            raise ValueError(f"Expected `xi` to have shape (6,) or (n, 6), got {np.shape(xi)}.")
        theta = np.linalg.norm(x[:, :3], axis=1)
        out = np.full(len(x), -np.inf)
        inside = np.isfinite(theta) & (theta < math.pi) & np.all(np.isfinite(x[:, 3:]), axis=1)
        if inside.any():
            th = theta[inside]
            safe = np.where(th < 1e-8, 1.0, th)
            jac = np.where(th < 1e-8, 1.0, 2.0 * (1.0 - np.cos(safe)) / safe**2)
            out[inside] = np.asarray(self.log_prob(from_chart(x[inside], T_ref))) + np.log(jac)
        return float(out[0]) if single else out


def pose_target(result: Any, object_model: Any, *, likelihood_params: Any = None,
                temperature: float | None = None) -> PoseTarget:
    """The target of ``result``'s pose distribution, as a :class:`PoseTarget`.

    Parameters
    ----------
    result : PoseResult
        From :func:`~certpose.estimation.pipeline.run_demo`, ``run_rgbd``, ``run_ycbv`` or
        ``estimate_pose``: its ``scene``, ``classification`` and ``T_world_camera`` are used.
    object_model : ObjectModel or BuiltObjectModel
        The object model the run used (:func:`demo_object_model` for the demo; for
        ``run_rgbd``/``run_ycbv`` with ``model_path``, ``object_from_points(points,
        FPFHBackbone(), voxel_size=0.005)``; a :class:`~certpose.geometry.appearance.BuiltObjectModel`
        is unwrapped).
    likelihood_params : LikelihoodParams, optional
        ``PoseParams.likelihood`` of the run (default: the defaults). Appearance descriptors are
        weighted by their backbone's ``similarity_scale`` as the pipeline does.
    temperature : float, optional
        Default: the run's (``result.sampling["temperature"]``), else the sampler's rule at the
        returned pose.

    Returns
    -------
    PoseTarget

    Raises
    ------
    ValueError
        ``result`` holds no scene field or classifier (e.g. a failed run).
    """
    from certpose.estimation.pipeline import likelihood_params_for
    from certpose.model.likelihood import PoseLikelihood
    from certpose.sampling.sampler import default_temperature

    scene = getattr(result, "scene", None)
    cls = getattr(result, "classification", None)
    if scene is None or cls is None:
        raise ValueError("`result` holds no scene field or classifier: a target needs a run that "
                         "built both (status " f"{getattr(result, 'status', '?')!r}).")
    model = getattr(object_model, "model", object_model)
    params = likelihood_params_for(likelihood_params, getattr(scene, "backbone", None))
    lik = PoseLikelihood(scene, cls, model, params=params)
    T_wc = np.eye(4) if result.T_world_camera is None else np.asarray(result.T_world_camera)
    if temperature is None:
        temperature = (result.sampling or {}).get("temperature")
    if temperature is None:
        temperature = default_temperature(lik, T_wc @ np.asarray(result.T_camera_object))
    return PoseTarget(lik, float(temperature), T_wc)


def demo_object_model(*, voxel_size: float = 0.005, num_views: int = 4,
                      revolution: str | None = "auto") -> Any:
    """The object model :func:`~certpose.estimation.pipeline.run_demo` builds (its defaults):
    the synthetic mug from ``num_views`` posed renders, body sampled by its symmetry.

    Returns
    -------
    ObjectModel
    """
    from certpose.data.synthetic import make_mug_scene
    from certpose.geometry.features import FPFHBackbone
    from certpose.geometry.objects import object_from_views

    # The object views do not depend on the scene's seed (the mug is rendered alone).
    views = make_mug_scene(rng=0).render_object_views(num_views)
    return object_from_views(views, FPFHBackbone(), voxel_size=voxel_size, name="mug",
                             revolution=revolution)
