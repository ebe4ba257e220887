r"""The exact marginal of a pose target about an object axis: a reference for samplers.

A known-answer test of a sampler compares its marginal about an object's axis (e.g. the demo
mug's symmetry axis) with the exact one.
A slice of eq. (1) along the axis is not that marginal: the marginal of the target
``exp(eq. (1) / T)`` integrates the other five degrees of freedom (the axis's tilt and the
translation) at every angle. :func:`axis_marginal` computes it by importance sampling in
coordinates made for it, independently of the samplers it judges:

.. math::

    R = R_{ref} \exp([s]_\times) \exp(\theta [a]_\times), \qquad
    t = p_{ref} + d - R c,

with ``a`` the object-frame axis, ``s`` a rotation vector orthogonal to ``a`` (the swing: the
axis's tilt), ``theta`` the twist (:func:`certpose.sampling.plots.axis_angles` returns exactly
``theta`` for these rotations), ``c`` a pivot on the axis (object frame), ``p_ref`` the pivot
under the reference pose and ``d`` its offset (m). The Haar measure of SO(3) in ``(s, theta)``
is ``sin|s| / |s| ds dtheta`` (the axis direction ``exp(s) a`` sweeps the sphere with that area
element and the twist is uniform on each fibre), so the marginal density of ``theta`` is

.. math::

    m(\theta) \propto \int_{|s| \le s_{max}} \int_{\mathbb{R}^3}
    \exp(f(R, t) / T) \, \frac{\sin |s|}{|s|} \, \mathrm{d}d \, \mathrm{d}s ,

restricted to swings up to ``max_swing_deg`` (a local marginal: a basin with the object upside
down is another region; :meth:`AxisMarginal.compare` reports a distribution's mass outside it).
The proposal draws ``theta`` uniformly on the circle, so no angle can be missed, and ``(s, d)``
from a 5-D Student t (4 dof) fitted to the weighted draws of pilot rounds, mixed with a three
times wider one (a fifth of the draws) so that the weights stay bounded where the conditional
shifts with the angle. The bin masses are self-normalised importance estimates; their standard
errors (delta method) are returned and :attr:`AxisMarginal.tv_error` turns them into the
expected total-variation error of the estimate itself.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation
from scipy.special import logsumexp

from certpose.sampling.chart import check_pose
from certpose.sampling.sampler import _t_log_norm
from solvers.validation import as_float_array

__all__ = ["AxisMarginal", "axis_marginal", "swing_angles"]

_DOF = 4.0
_WIDE = 3.0  # scale of the defensive component
_WIDE_SHARE = 0.2


def _unit_axis(axis: ArrayLike) -> NDArray[np.float64]:
    a = as_float_array(axis, "axis")
    if a.shape != (3,):
        raise ValueError(f"Expected `axis` to have shape (3,), got {a.shape}.")
    n = float(np.linalg.norm(a))
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError("Expected `axis` to be a finite non-zero vector.")
    return a / n


def swing_angles(rotations: ArrayLike, axis: ArrayLike, T_ref: ArrayLike) -> NDArray[np.float64]:
    """(n,) angle (rad) between the object axis under each rotation and under the reference.

    Parameters
    ----------
    rotations : (n, 3, 3)
        Rotations ``R_camera_object``.
    axis : (3,)
        Object-frame axis (any length).
    T_ref : (4, 4)
        Reference pose ``T_camera_object``.
    """
    a = _unit_axis(axis)
    T_ref = check_pose(T_ref)
    R = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    return np.arccos(np.clip((R @ a) @ (T_ref[:3, :3] @ a), -1.0, 1.0))


def _t_logpdf(z: NDArray[np.float64], dim: int) -> NDArray[np.float64]:
    """log density of a standard multivariate t (``_DOF`` dof) at whitened points ``z`` (n, dim)."""
    return _t_log_norm(_DOF, dim) - 0.5 * (_DOF + dim) * np.log1p(np.einsum("ij,ij->i", z, z) / _DOF)


@dataclass(frozen=True)
class _Proposal:
    mean: NDArray[np.float64]  # (5,)
    chol: NDArray[np.float64]  # (5, 5) lower Cholesky factor of the scale matrix

    def draw(self, n: int, rng: np.random.Generator) -> NDArray[np.float64]:
        wide = rng.random(n) < _WIDE_SHARE
        g = rng.standard_normal((n, 5)) / np.sqrt(rng.chisquare(_DOF, n) / _DOF)[:, None]
        g[wide] *= _WIDE
        return self.mean + g @ self.chol.T

    def logpdf(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        from scipy.linalg import solve_triangular

        z = solve_triangular(self.chol, (x - self.mean).T, lower=True).T
        logdet = float(np.log(np.diag(self.chol)).sum())
        narrow = _t_logpdf(z, 5) - logdet
        wide = _t_logpdf(z / _WIDE, 5) - logdet - 5 * math.log(_WIDE)
        return np.logaddexp(math.log1p(-_WIDE_SHARE) + narrow, math.log(_WIDE_SHARE) + wide)


@dataclass(frozen=True)
class AxisMarginal:
    """The marginal of a pose target over the rotation about an object axis (see the module).

    Attributes
    ----------
    edges_deg : (B + 1,)
        Bin edges (deg) of the twist angle, from -180 to 180.
    mass : (B,)
        The target's mass per bin (sums to 1), restricted to swings up to ``max_swing_deg``.
    stderr : (B,)
        Standard error of each bin's estimate (delta method for self-normalised weights).
    ess : float
        Kish's effective sample size of the final draws.
    draws : int
        Number of final draws.
    max_swing_deg : float
        The region: the axis within this angle (deg) of the reference's.
    axis : (3,)
        Unit object-frame axis.
    T_ref : (4, 4)
        Reference pose (angles are measured from it).
    axes : (n, 3)
        The final draws' axis directions (scene frame, unit).
    offsets : (n, 3)
        The final draws' pivot offsets from the reference's pivot (scene frame, m).
    weights : (n,)
        The final draws' normalised importance weights (zero outside the region).
    """

    edges_deg: NDArray[np.float64]
    mass: NDArray[np.float64]
    stderr: NDArray[np.float64]
    ess: float
    draws: int
    max_swing_deg: float
    axis: NDArray[np.float64]
    T_ref: NDArray[np.float64]
    axes: NDArray[np.float64]
    offsets: NDArray[np.float64]
    weights: NDArray[np.float64]

    def mass_near_axis(self, max_tilt_deg: float = 5.0, max_offset: float = 0.01, *,
                       direction: ArrayLike | None = None) -> float:
        """The target's mass (in the region) whose axis lies within ``max_tilt_deg`` of
        ``direction`` (scene frame; default the reference's axis) and whose pivot lies within
        ``max_offset`` (m) of the reference's axis line: the share of the target whose axis direction is
        within 5 deg and whose axis position is within 1 cm of the reference's."""
        a_ref = self.T_ref[:3, :3] @ self.axis
        up = a_ref if direction is None else _unit_axis(direction)
        tilt = np.degrees(np.arccos(np.clip(self.axes @ up, -1.0, 1.0)))
        d = self.offsets
        off = np.linalg.norm(d - np.outer(d @ a_ref, a_ref), axis=1)
        return float(self.weights[(tilt <= max_tilt_deg) & (off <= max_offset)].sum())

    @property
    def tv_error(self) -> float:
        """Expected total-variation distance of this estimate from the exact marginal
        (``0.5 * sqrt(2 / pi) * sum(stderr)``, each bin's error taken as normal)."""
        return float(0.5 * math.sqrt(2.0 / math.pi) * self.stderr.sum())

    def histogram(self, rotations: ArrayLike, weights: ArrayLike) -> tuple[NDArray[np.float64], float]:
        """A weighted set of rotations binned like :attr:`mass`, restricted to the region.

        Returns
        -------
        mass : (B,)
            Normalised mass per bin of the rotations within ``max_swing_deg`` (zeros if none).
        outside : float
            The share of the weights outside the region (e.g. an upside-down basin).
        """
        from certpose.sampling.plots import axis_angles

        R = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
        w = as_float_array(weights, "weights").reshape(-1)
        if w.shape[0] != R.shape[0]:
            raise ValueError(f"Expected `weights` to have shape ({R.shape[0]},), got {w.shape}.")
        if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            raise ValueError("Expected `weights` to be finite, non-negative and not all zero.")
        w = w / w.sum()
        inside = swing_angles(R, self.axis, self.T_ref) <= math.radians(self.max_swing_deg)
        theta = np.degrees(axis_angles(R[inside], self.axis, self.T_ref))
        h, _ = np.histogram(theta, self.edges_deg, weights=w[inside])
        total = h.sum()
        return (h / total if total > 0 else h), float(1.0 - w[inside].sum())

    def compare(self, distribution: object) -> tuple[float, float]:
        """(total variation from :attr:`mass`, mass outside the region) of a distribution with
        ``rotations`` and ``weights`` (e.g. :class:`~certpose.sampling.PoseDistribution`)."""
        h, outside = self.histogram(distribution.rotations, distribution.weights)  # type: ignore[attr-defined]
        return float(0.5 * np.abs(h - self.mass).sum()), outside


def _poses(theta: NDArray[np.float64], x: NDArray[np.float64], basis: NDArray[np.float64],
           a: NDArray[np.float64], T_ref: NDArray[np.float64], pivot: NDArray[np.float64]) -> NDArray[np.float64]:
    s = x[:, :2] @ basis  # (n, 3) swing rotation vectors, orthogonal to a
    R_rel = (Rotation.from_rotvec(s) * Rotation.from_rotvec(theta[:, None] * a)).as_matrix()
    R = T_ref[:3, :3] @ R_rel
    p_ref = T_ref[:3, :3] @ pivot + T_ref[:3, 3]
    T = np.zeros((len(theta), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = p_ref + x[:, 2:] - R @ pivot
    T[:, 3, 3] = 1.0
    return T


def _log_weights(log_target: Callable[[NDArray[np.float64]], ArrayLike], theta: NDArray[np.float64],
                 x: NDArray[np.float64], prop: _Proposal, basis: NDArray[np.float64], a: NDArray[np.float64],
                 T_ref: NDArray[np.float64], pivot: NDArray[np.float64], temperature: float,
                 max_swing: float, chunk: int, bar: Any) -> NDArray[np.float64]:
    r = np.linalg.norm(x[:, :2], axis=1)
    lw = np.full(len(theta), -np.inf)
    keep = np.flatnonzero(r <= max_swing)
    bar.update(len(theta) - len(keep))
    for k in range(0, len(keep), chunk):
        idx = keep[k:k + chunk]
        f = np.asarray(log_target(_poses(theta[idx], x[idx], basis, a, T_ref, pivot)), dtype=np.float64)
        if f.shape != (len(idx),):
            raise ValueError(f"Expected `log_target` to return shape ({len(idx)},), got {f.shape}.")
        lw[idx] = f / temperature
        bar.update(len(idx))
    jac = np.log(np.sinc(np.minimum(r, max_swing) / math.pi))  # sin r / r (r < pi where kept)
    lw = lw + jac - prop.logpdf(x)
    lw[~np.isfinite(lw)] = -np.inf
    return lw


def _fit(x: NDArray[np.float64], lw: NDArray[np.float64], prev: _Proposal, inflate: float) -> _Proposal:
    w = np.exp(lw - lw.max())
    w /= w.sum()
    mean = w @ x
    dx = x - mean
    cov = inflate**2 * ((dx * w[:, None]).T @ dx)
    ess = 1.0 / float(np.sum(w**2))
    if ess < 50:
        # Few effective draws: the proposal is far too narrow (the heavy draws lie in its tails)
        # or too wide; keep the previous scale in the sum so that it can grow but not collapse.
        cov = cov + prev.chol @ prev.chol.T
    if not np.all(np.isfinite(cov)):
        return prev
    try:
        chol = np.linalg.cholesky(cov + 1e-12 * np.eye(5))
    except np.linalg.LinAlgError:
        return prev
    return _Proposal(mean, chol)


def axis_marginal(
    log_target: Callable[[NDArray[np.float64]], ArrayLike],
    T_ref: ArrayLike,
    axis: ArrayLike,
    *,
    temperature: float = 1.0,
    pivot: ArrayLike = (0.0, 0.0, 0.0),
    bin_deg: float = 5.0,
    max_swing_deg: float = 30.0,
    draws: int = 200_000,
    pilot_draws: int = 20_000,
    pilot_rounds: int = 3,
    initial_scale: tuple[float, float] = (0.035, 0.003),
    rng: np.random.Generator | int | None = None,
    chunk: int = 8192,
    progress: bool = False,
) -> AxisMarginal:
    """The marginal of ``exp(log_target / temperature)`` over the rotation about ``axis``.

    Parameters
    ----------
    log_target : callable
        ``(n, 4, 4)`` poses ``T_camera_object`` -> ``(n,)`` log target (e.g. a
        :class:`~certpose.model.likelihood.PoseLikelihood`).
    T_ref : (4, 4)
        Reference pose: angles are measured from it, swings from its axis direction (e.g. the
        ground truth).
    axis : (3,)
        Object-frame axis (any length).
    temperature : float
        The target is ``exp(log_target / temperature)`` (> 0).
    pivot : (3,)
        A point on the axis (object frame, m): the proposal's translation is centred on it, so
        turning about the axis does not move the proposal.
    bin_deg : float
        Bin width (deg); must divide 360.
    max_swing_deg : float
        The region integrated: the axis within this angle of the reference's (0 < it < 180).
    draws, pilot_draws, pilot_rounds : int
        Final draws; draws per pilot round and pilot rounds (each fits the proposal of the
        next to its weighted draws).
    initial_scale : (float, float)
        The first pilot's scales of the swing (rad) and the translation (m).
    rng : numpy.random.Generator or int or None
        Random source.
    chunk : int
        Poses per call of ``log_target``.
    progress : bool
        A progress bar over the target's evaluations (tqdm, when installed).

    Returns
    -------
    AxisMarginal
    """
    T_ref = check_pose(T_ref)
    a = _unit_axis(axis)
    c = as_float_array(pivot, "pivot")
    if c.shape != (3,):
        raise ValueError(f"Expected `pivot` to have shape (3,), got {c.shape}.")
    if not (np.isfinite(temperature) and temperature > 0):
        raise ValueError(f"Expected `temperature` > 0, got {temperature}.")
    nbins = 360.0 / bin_deg if bin_deg > 0 else 0.0
    if not (bin_deg > 0 and abs(nbins - round(nbins)) < 1e-9):
        raise ValueError(f"Expected `bin_deg` to divide 360, got {bin_deg}.")
    if not 0 < max_swing_deg < 180:
        raise ValueError(f"Expected 0 < `max_swing_deg` < 180, got {max_swing_deg}.")
    for name, v in (("draws", draws), ("pilot_draws", pilot_draws), ("chunk", chunk)):
        if int(v) != v or v < 1:
            raise ValueError(f"Expected `{name}` to be a positive integer, got {v}.")
    if int(pilot_rounds) != pilot_rounds or pilot_rounds < 0:
        raise ValueError(f"Expected `pilot_rounds` to be a non-negative integer, got {pilot_rounds}.")
    sr, st = (float(v) for v in initial_scale)
    if not (sr > 0 and st > 0):
        raise ValueError(f"Expected positive `initial_scale`, got {initial_scale}.")
    gen = np.random.default_rng(rng)
    # An orthonormal basis of the plane orthogonal to the axis.
    u = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    basis = np.stack([u, np.cross(a, u)])
    max_swing = math.radians(max_swing_deg)
    prop = _Proposal(np.zeros(5), np.diag([sr, sr, st, st, st]))

    from certpose.sampling.sampler import _progress

    bar = _progress(int(pilot_rounds) * int(pilot_draws) + int(draws), "axis marginal", progress)

    def run(n: int, p: _Proposal) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        theta = gen.uniform(-math.pi, math.pi, n)
        x = p.draw(n, gen)
        return theta, x, _log_weights(log_target, theta, x, p, basis, a, T_ref, c, float(temperature),
                                      max_swing, int(chunk), bar)

    try:
        for _ in range(int(pilot_rounds)):
            _, x, lw = run(int(pilot_draws), prop)
            if np.isfinite(lw).any():
                prop = _fit(x, lw, prop, inflate=1.5)
        theta, x, lw = run(int(draws), prop)
    finally:
        bar.close()
    if not np.isfinite(lw).any():
        raise RuntimeError("Every draw has zero target density: is `T_ref` near the target's mass?")
    w = np.exp(lw - logsumexp(lw))
    edges = np.linspace(-180.0, 180.0, int(round(nbins)) + 1)
    b = np.clip(np.searchsorted(edges, np.degrees(theta), side="right") - 1, 0, len(edges) - 2)
    mass = np.bincount(b, weights=w, minlength=len(edges) - 1)
    # Delta method: var(p_b) = sum_i w_i^2 (1[i in b] - p_b)^2 for self-normalised weights.
    w2 = w**2
    in_b = np.bincount(b, weights=w2, minlength=len(edges) - 1)
    var = in_b * (1.0 - mass) ** 2 + (w2.sum() - in_b) * mass**2
    axes = (T_ref[:3, :3] @ Rotation.from_rotvec(x[:, :2] @ basis).as_matrix() @ a)
    return AxisMarginal(edges_deg=edges, mass=mass, stderr=np.sqrt(var), ess=float(1.0 / w2.sum()),
                        draws=int(draws), max_swing_deg=float(max_swing_deg), axis=a, T_ref=T_ref,
                        axes=axes, offsets=x[:, 2:].copy(), weights=w)
