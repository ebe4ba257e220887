"""A weighted particle set over object poses ``T_camera_object``.

Tangent chart (used by :meth:`PoseDistribution.tangent`): a pose ``(R, t)`` relative to a
reference ``(R0, t0)`` is the 6-vector ``(log(R0^T R), t - t0)``, rotation vector in radians
(object-frame perturbation) followed by the translation offset in metres (camera frame).
"""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation
from scipy.special import logsumexp

__all__ = ["PoseDistribution", "PoseMode"]

logger = logging.getLogger(__name__)

_ORTHO_TOL = 1e-6


def _check_rotations(rotations: NDArray[np.float64]) -> None:
    if rotations.ndim != 3 or rotations.shape[1:] != (3, 3):
        raise ValueError(f"Expected `rotations` to have shape (n, 3, 3), got {rotations.shape}.")
    if not np.all(np.isfinite(rotations)):
        raise ValueError("`rotations` contains NaN or infinite values.")
    err = np.abs(np.einsum("nji,njk->nik", rotations, rotations) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rotations)
    bad = np.flatnonzero((err > _ORTHO_TOL) | (det < 0))
    if bad.size:
        raise ValueError(
            f"`rotations[{bad[0]}]` is not a rotation (|R^T R - I| = {err[bad[0]]:.2e}, "
            f"det = {det[bad[0]]:.3f}); {bad.size} of {len(rotations)} are invalid."
        )


def _check_query(R: ArrayLike, t: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """One query pose: ``R`` (3, 3) a rotation, ``t`` (3,) finite."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"Expected `R` to have shape (3, 3), got {R.shape}.")
    if t.size != 3 or not np.all(np.isfinite(t)):
        raise ValueError(f"Expected `t` to hold 3 finite values, got shape {t.shape}.")
    _check_rotations(R[None])
    return R, t.reshape(3)


def _axis_basis(axis: ArrayLike) -> NDArray[np.float64]:
    """(3, 3) orthonormal rows: two unit vectors perpendicular to ``axis``, then ``axis``."""
    a = np.asarray(axis, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"Expected `axis` to have shape (3,), got {a.shape}.")
    n = float(np.linalg.norm(a))
    if not (np.isfinite(n) and n > 0):
        raise ValueError(f"Expected `axis` to be a finite non-zero vector, got {a}.")
    a = a / n
    e1 = np.cross(a, np.eye(3)[int(np.argmin(np.abs(a)))])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(a, e1), a])


def _basins(A: NDArray[np.float64], w: NDArray[np.float64], cos_radius: float) -> NDArray[np.float64]:
    """Each unit axis's basin mean (n, 3): from the heaviest axis left, the weighted mean of the
    axes within the radius, refined twice; those within the radius of it join the basin and leave;
    until none is left. Every axis lies within the radius of its basin's mean."""
    left = np.ones(len(A), dtype=bool)
    out = np.empty_like(A)
    while left.any():
        idx = np.flatnonzero(left)
        seed = idx[np.argmax(w[idx])]
        m = A[seed]
        for _ in range(3):
            near = left & (A @ m >= cos_radius)
            s = w[near] @ A[near]
            n = float(np.linalg.norm(s))
            if n == 0.0:
                break
            m = s / n
        near = left & (A @ m >= cos_radius)
        if not near.any():  # the refined mean moved off every member: the seed alone
            m = A[seed]
            near = np.zeros(len(A), dtype=bool)
            near[seed] = True
        out[near] = m
        left &= ~near
    return out


#: A mode with fewer distinct particles has no covariance of its own for the kernel density.
_MIN_MODE_PARTICLES = 12


def _gaussian_kernel(cov: NDArray[np.float64], count: float) -> tuple[NDArray[np.float64], float]:
    """Cholesky factor of ``h^2 cov`` with Scott's ``h = count^(-1/10)`` (6-D) and the
    Gaussian's log-normaliser."""
    h2 = float(count) ** (-2.0 / 10.0)
    L = np.linalg.cholesky(h2 * cov + 1e-12 * np.eye(6))
    return L, float(-0.5 * 6 * np.log(2 * np.pi) - np.sum(np.log(np.diag(L))))


@dataclass(frozen=True, eq=False)
class _ModeKernels:
    """Per-mode Gaussian kernels: ``label`` (n,) the mode of each particle, ``chol`` (M, 6, 6)
    and ``log_norm`` (M,) each mode's kernel, ``pivots`` (M, 3) each mode's pivot (object frame,
    m; see :meth:`PoseDistribution.log_density`), ``centres`` each mode's mean ``(R, t + R c)``."""

    label: NDArray[np.int64]
    chol: NDArray[np.float64]
    log_norm: NDArray[np.float64]
    pivots: NDArray[np.float64]
    centres: list


def _pivot(R: NDArray[np.float64], t: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
    """(3,) the object point ``c`` whose camera position ``R_i c + t_i`` varies least over the
    weighted poses (least squares; the minimum-norm one when a turn leaves a line of them
    fixed: the axis). A turn about an axis through ``c`` then leaves the chart's translation
    part fixed."""
    Rm = np.einsum("n,nij->ij", w, R)
    A = (R - Rm) * np.sqrt(w)[:, None, None]
    b = (t - w @ t) * np.sqrt(w)[:, None]
    c, *_ = np.linalg.lstsq(A.reshape(-1, 3), -b.reshape(-1), rcond=1e-6)
    return c


@dataclass(frozen=True, eq=False)
class PoseMode:
    """One cluster of a :class:`PoseDistribution`.

    Attributes
    ----------
    rotation : (3, 3)
        Weighted Karcher mean rotation of the cluster.
    translation : (3,)
        Weighted mean translation (m).
    covariance : (6, 6)
        Weighted covariance in the tangent chart around the mean (rad^2, m^2).
    mass : float
        Sum of the cluster's weights.
    num_particles : int
    """

    rotation: NDArray[np.float64]
    translation: NDArray[np.float64]
    covariance: NDArray[np.float64]
    mass: float
    num_particles: int

    @property
    def T(self) -> NDArray[np.float64]:
        """(4, 4) mean pose."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.rotation, self.translation
        return T


@dataclass(frozen=True)
class PoseDistribution:
    """Weighted particles of ``T_camera_object``.

    Parameters
    ----------
    rotations : (n, 3, 3) float64
        Rotation parts of ``T_camera_object``.
    translations : (n, 3) float64
        Translation parts, metres.
    weights : (n,) float64
        Normalised importance weights (positive, summing to 1). Use :meth:`from_log_weights`
        for unnormalised log-weights.
    log_weights : (n,) float64 or None
        Raw log importance ratios, kept for the Pareto-k diagnostic; None after resampling.
    """

    rotations: NDArray[np.float64]
    translations: NDArray[np.float64]
    weights: NDArray[np.float64]
    log_weights: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        R = np.array(self.rotations, dtype=np.float64)
        t = np.array(self.translations, dtype=np.float64)
        w = np.array(self.weights, dtype=np.float64)
        if R.ndim == 3 and R.shape[0] == 0:
            raise ValueError("Expected a non-empty particle set, got 0 particles.")
        _check_rotations(R)
        n = R.shape[0]
        if t.shape != (n, 3):
            raise ValueError(f"Expected `translations` to have shape ({n}, 3), got {t.shape}.")
        if not np.all(np.isfinite(t)):
            raise ValueError("`translations` contains NaN or infinite values.")
        if w.shape != (n,):
            raise ValueError(f"Expected `weights` to have shape ({n},), got {w.shape}.")
        if not np.all(np.isfinite(w)):
            raise ValueError("`weights` contains NaN or infinite values.")
        if np.any(w <= 0):
            raise ValueError(f"`weights` must be positive; {int(np.sum(w <= 0))} are <= 0.")
        if abs(w.sum() - 1.0) > 1e-8:
            raise ValueError(f"`weights` must sum to 1, got {w.sum():.6g}.")
        lw = None
        if self.log_weights is not None:
            lw = np.array(self.log_weights, dtype=np.float64)
            if lw.shape != (n,):
                raise ValueError(f"Expected `log_weights` to have shape ({n},), got {lw.shape}.")
            lw.setflags(write=False)
        for a in (R, t, w):
            a.setflags(write=False)
        object.__setattr__(self, "rotations", R)
        object.__setattr__(self, "translations", t)
        object.__setattr__(self, "weights", w)
        object.__setattr__(self, "log_weights", lw)

    @classmethod
    def from_log_weights(
        cls, rotations: ArrayLike, translations: ArrayLike, log_weights: ArrayLike
    ) -> PoseDistribution:
        """Build from unnormalised log-weights (``-inf`` is refused, NaN is refused)."""
        lw = np.asarray(log_weights, dtype=np.float64)
        n = np.shape(rotations)[0] if np.ndim(rotations) else 0
        if lw.ndim != 1 or lw.size == 0 or lw.size != n:
            raise ValueError(f"Expected `log_weights` to have shape ({n},), n > 0, got {lw.shape}.")
        if not np.all(np.isfinite(lw)):
            raise ValueError("`log_weights` contains NaN or infinite values.")
        w = np.exp(lw - lw.max())
        w /= w.sum()
        # Underflowed weights would be refused as zero: floor them at the smallest positive float.
        w = np.maximum(w, np.finfo(np.float64).tiny)
        w /= w.sum()
        return cls(np.asarray(rotations), np.asarray(translations), w, log_weights=lw)

    def __len__(self) -> int:
        return int(self.weights.shape[0])

    @property
    def poses(self) -> NDArray[np.float64]:
        """(n, 4, 4) homogeneous ``T_camera_object``."""
        T = np.zeros((len(self), 4, 4))
        T[:, :3, :3] = self.rotations
        T[:, :3, 3] = self.translations
        T[:, 3, 3] = 1.0
        return T

    @property
    def ess(self) -> float:
        """Kish effective sample size ``1 / sum(w^2)``."""
        return float(1.0 / np.sum(self.weights**2))

    def pareto_k(self) -> float:
        """Pareto-k of PSIS on the raw log-weights (arviz); k > 0.7 means unreliable weights.

        Raises
        ------
        ValueError
            If the distribution carries no raw log-weights (e.g. after resampling).
        """
        if self.log_weights is None:
            raise ValueError("Pareto-k needs the raw `log_weights`; this distribution has none.")
        with warnings.catch_warnings():
            # arviz announces its refactor on import; psislw is unaffected.
            warnings.simplefilter("ignore", FutureWarning)
            import arviz

        _, k = arviz.psislw(self.log_weights.copy())
        return float(np.asarray(k))

    def resample(
        self, n: int | None = None, *, rng: np.random.Generator | int | None = None
    ) -> PoseDistribution:
        """Systematic resampling to ``n`` equally weighted particles (default: same size)."""
        if n is not None and (int(n) != n or n <= 0):
            raise ValueError(f"Expected `n` to be a positive integer, got {n!r}.")
        n = len(self) if n is None else int(n)
        rng = np.random.default_rng(rng)
        cdf = np.cumsum(self.weights)
        cdf[-1] = 1.0
        u = (rng.random() + np.arange(n)) / n
        idx = np.searchsorted(cdf, u, side="right")
        return PoseDistribution(self.rotations[idx], self.translations[idx], np.full(n, 1.0 / n))

    def with_model_error(self, rotation_sigma: float, translation_sigma: float, *,
                         centre: ArrayLike = (0.0, 0.0, 0.0), copies: int = 1, dof: float = math.inf,
                         axis: ArrayLike | None = None, spin_sigma: float | None = None,
                         rng: np.random.Generator | int | None = None) -> PoseDistribution:
        """This distribution convolved with a model-error kernel: each particle turned by a
        random rotation about ``centre`` (object frame, metres) and shifted.

        A pose distribution drawn from eq. (1) is as sharp as eq. (1) is, but the object model
        and the scene field are not exact: a pose a few degrees off can explain the data as well
        under a slightly different model. The kernel carries that error into the distribution:
        ``T' = T exp(w) (about centre) + d``, ``w ~ N(0, rotation_sigma^2 I)`` (radians, object
        frame), ``d ~ N(0, translation_sigma^2 I)`` (metres, the particles' frame). With a finite
        ``dof`` both are scaled by one draw of ``sqrt(dof / chi2(dof))`` per particle: a
        multivariate Student t kernel, whose core is as narrow as the Gaussian's and whose tails
        are heavier (a model that is right for most poses and off by more for a few).

        With ``axis`` (an object's axis of revolution) the rotation splits into a *tilt* (the
        components of ``w`` perpendicular to ``axis``, ``rotation_sigma`` each) and a *spin*
        (its component along ``axis``, ``spin_sigma``): a body of revolution's error about its
        own axis need not be that about the axes across it.

        Parameters
        ----------
        rotation_sigma : float
            Radians per axis (>= 0); with ``axis``, per tilt axis.
        translation_sigma : float
            Metres per axis (>= 0).
        centre : (3,) array_like
            Object-frame point the rotations turn about (e.g. the model's centroid).
        copies : int
            Perturbed copies of each particle (>= 1); weights are shared among them.
        dof : float
            Degrees of freedom of the Student t kernel (> 0; ``inf``, the default: Gaussian).
        axis : (3,) array_like or None
            Object-frame direction of the axis of revolution (normalised here; not zero). Turns
            are still about ``centre``: pass a point on the axis.
        spin_sigma : float or None
            Radians about ``axis`` (>= 0; ``None``: ``rotation_sigma``). Only with ``axis``.
        rng : numpy Generator, int or None

        Returns
        -------
        PoseDistribution
            ``copies * len(self)`` particles, without ``log_weights``.
        """
        if not (dof > 0):
            raise ValueError(f"Expected `dof` > 0, got {dof}.")
        for name, v in (("rotation_sigma", rotation_sigma), ("translation_sigma", translation_sigma)):
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"Expected `{name}` to be finite and >= 0, got {v}.")
        if int(copies) != copies or copies < 1:
            raise ValueError(f"Expected `copies` to be a positive integer, got {copies!r}.")
        scales = np.full(3, float(rotation_sigma))
        basis = np.eye(3)
        if axis is not None:
            basis = _axis_basis(axis)
            if spin_sigma is not None:
                if not (np.isfinite(spin_sigma) and spin_sigma >= 0):
                    raise ValueError(f"Expected `spin_sigma` to be finite and >= 0, got {spin_sigma}.")
                scales[2] = float(spin_sigma)
        elif spin_sigma is not None:
            raise ValueError("`spin_sigma` needs `axis`.")
        c = np.asarray(centre, dtype=np.float64).reshape(3)
        gen = np.random.default_rng(rng)
        R = np.repeat(self.rotations, int(copies), axis=0)
        t = np.repeat(self.translations, int(copies), axis=0)
        w = np.repeat(self.weights, int(copies)) / int(copies)
        k = np.ones((len(w), 1))
        if math.isfinite(dof):
            k = np.sqrt(float(dof) / gen.chisquare(float(dof), size=(len(w), 1)))
        # Rows of `basis`: two tilt directions, then the axis (the identity without an axis).
        E = Rotation.from_rotvec(k * (gen.normal(size=(len(w), 3)) * scales) @ basis).as_matrix()
        R2 = R @ E
        t2 = t + R @ c - R2 @ c + k * gen.normal(scale=float(translation_sigma), size=(len(w), 3))
        return PoseDistribution(R2, t2, w)

    def with_tilt_scale(self, scale: float, *, axis: ArrayLike, centre: ArrayLike = (0.0, 0.0, 0.0),
                        basin_deg: float = 30.0) -> PoseDistribution:
        """This distribution with its tilt across an axis of revolution scaled by ``scale``.

        The particles' axes (``R @ axis``) are grouped into basins (a basin: the axes within
        ``basin_deg`` of its weighted mean axis, taken greedily from the heaviest particle left;
        an upright and an upside-down basin are two). Each particle is then turned, about its own
        point ``centre`` and by the least rotation, so that its axis's angle to its basin's mean
        axis is ``scale`` times what it was. Spin about the axis, the point's position and the
        weights are kept. For a basin whose tilt is Gaussian this is the tilt marginal tempered
        by ``scale**2`` (a variance ``scale**2`` times as large), the other coordinates left as
        they were.

        Parameters
        ----------
        scale : float
            Factor on every particle's tilt from its basin's mean axis (>= 0; 1 returns the same
            particles; 0 puts every axis on its basin's mean).
        axis : (3,) array_like
            Object-frame direction of the axis of revolution (not zero).
        centre : (3,) array_like
            Object-frame point on the axis that each particle turns about (metres).
        basin_deg : float
            Radius of a basin about its mean axis (degrees, in (0, 90)).

        Returns
        -------
        PoseDistribution
            As many particles, the same weights, without ``log_weights``.
        """
        if not (np.isfinite(scale) and scale >= 0):
            raise ValueError(f"Expected `scale` to be finite and >= 0, got {scale}.")
        if not (0 < basin_deg < 90):
            raise ValueError(f"Expected `basin_deg` in (0, 90), got {basin_deg}.")
        a = _axis_basis(axis)[2]
        c = np.asarray(centre, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(c)):
            raise ValueError(f"Expected `centre` to be finite, got {c}.")
        if scale == 1.0:
            return PoseDistribution(self.rotations, self.translations, self.weights)
        A = self.rotations @ a
        m = _basins(A, self.weights, math.cos(math.radians(basin_deg)))
        # The least rotation taking each axis to `scale` of its angle from the basin's mean.
        cross = np.cross(A, m)
        sin = np.linalg.norm(cross, axis=1)
        theta = np.arctan2(sin, np.einsum("ij,ij->i", A, m))
        u = np.divide(cross, sin[:, None], out=np.zeros_like(cross), where=sin[:, None] > 1e-12)
        E = Rotation.from_rotvec(u * ((1.0 - float(scale)) * theta)[:, None]).as_matrix()
        R2 = E @ self.rotations
        p = self.rotations @ c + self.translations
        return PoseDistribution(R2, p - R2 @ c, self.weights)

    def tangent(self, R0: ArrayLike, t0: ArrayLike) -> NDArray[np.float64]:
        """(n, 6) chart coordinates ``(log(R0^T R), t - t0)`` around ``(R0, t0)``."""
        R0 = np.asarray(R0, dtype=np.float64)
        rel = np.einsum("ji,njk->nik", R0, self.rotations)
        rv = Rotation.from_matrix(rel).as_rotvec()
        return np.hstack([rv, self.translations - np.asarray(t0, dtype=np.float64).reshape(1, 3)])

    def mean_and_covariance(self, *, iterations: int = 10) -> tuple[NDArray, NDArray, NDArray]:
        """Weighted Karcher mean rotation, mean translation, and 6x6 tangent covariance.

        Returns ``(R_mean (3,3), t_mean (3,), cov (6,6))`` in the chart of the module docstring.
        """
        i0 = int(np.argmax(self.weights))
        R0, t0 = self.rotations[i0], np.asarray(self.weights @ self.translations)
        for _ in range(iterations):
            d = self.weights @ self.tangent(R0, t0)[:, :3]
            R0 = R0 @ Rotation.from_rotvec(d).as_matrix()
            if np.linalg.norm(d) < 1e-12:
                break
        X = self.tangent(R0, t0)
        cov = np.einsum("n,ni,nj->ij", self.weights, X, X)
        return R0, t0, cov

    def modes(
        self,
        *,
        rotation_scale: float = 0.1,
        translation_scale: float = 0.01,
        max_points: int = 2000,
        rng: np.random.Generator | int | None = 0,
    ) -> list[PoseMode]:
        """Clusters of the particles with their mass, heaviest first.

        Single-linkage clustering (``scipy.cluster.hierarchy``) cut at distance 1 in the metric
        ``sqrt((theta / rotation_scale)^2 + (|dt| / translation_scale)^2)`` (``theta`` from the
        chordal distance of the rotations, rad; ``dt`` in m): a continuous arc of poses (a hidden
        handle) stays one mode. At most ``max_points`` particles (a systematic resampling) are
        clustered; every particle then joins the cluster of its nearest clustered particle.
        """
        labels = self._cluster_labels(rotation_scale=rotation_scale,
                                      translation_scale=translation_scale,
                                      max_points=max_points, rng=rng)
        out = []
        for lab in np.unique(labels):
            idx = np.flatnonzero(labels == lab)
            mass = float(self.weights[idx].sum())
            R, t, cov = self._subset(idx).mean_and_covariance()
            out.append(PoseMode(R, t, cov, mass, len(idx)))
        return sorted(out, key=lambda m: -m.mass)

    def _subset(self, idx: NDArray[np.int64]) -> PoseDistribution:
        """The particles ``idx`` with their weights renormalised."""
        w = self.weights[idx]
        return PoseDistribution(self.rotations[idx], self.translations[idx], w / w.sum())

    def _cluster_labels(self, *, rotation_scale: float = 0.1, translation_scale: float = 0.01,
                        max_points: int = 2000,
                        rng: np.random.Generator | int | None = 0) -> NDArray[np.int64]:
        """(n,) cluster label of every particle (see :meth:`modes`)."""
        from scipy.cluster.hierarchy import fcluster, linkage
        from scipy.spatial import cKDTree

        for name, v in (("rotation_scale", rotation_scale), ("translation_scale", translation_scale)):
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"Expected `{name}` to be positive and finite, got {v}.")
        if int(max_points) < 1:
            raise ValueError(f"Expected `max_points` >= 1, got {max_points}.")
        # Chordal distance |R1 - R2|_F = 2 sqrt(2) sin(theta / 2) ~ sqrt(2) theta.
        feats = np.hstack([self.rotations.reshape(-1, 9) / (np.sqrt(2) * rotation_scale),
                           self.translations / translation_scale])
        sub = self if len(self) <= max_points else self.resample(int(max_points), rng=rng)
        sub_feats = np.hstack([sub.rotations.reshape(-1, 9) / (np.sqrt(2) * rotation_scale),
                               sub.translations / translation_scale])
        uniq = np.unique(sub_feats, axis=0)
        labels_u = (np.ones(1, dtype=int) if len(uniq) == 1
                    else fcluster(linkage(uniq, method="single"), t=1.0, criterion="distance"))
        _, nearest = cKDTree(uniq).query(feats)
        return np.asarray(labels_u[nearest], dtype=np.int64)

    def _kernel_count(self) -> float:
        """Sample size behind Scott's bandwidth: the ESS, at most the number of distinct
        particles (a resampled set repeats particles; its ESS counts each copy)."""
        distinct = len(np.unique(self.translations, axis=0))
        return float(max(min(self.ess, distinct), 1.0))

    def _kernel(self) -> tuple[NDArray[np.float64], float]:
        """Cholesky factor of the one-mode kernel covariance ``h^2 C`` (``C`` the weighted
        tangent covariance of all the particles) and the kernel's log-normaliser."""
        _, _, cov = self.mean_and_covariance()
        return _gaussian_kernel(cov, self._kernel_count())

    def _mode_kernels(self, *, per_mode: bool = True, pivot: bool = True) -> _ModeKernels:
        """The kernel of every particle: that of its mode (see :meth:`log_density`).

        ``per_mode=False`` treats all the particles as one mode and ``pivot=False`` keeps the
        object origin as the chart's translation point (both off: one covariance for the whole
        set, the estimator before the modes; kept for ``examples/benchmarks/bench_samplers.py --kde-check``).
        """
        labels = self._cluster_labels() if per_mode else np.zeros(len(self), dtype=np.int64)
        modes = []
        for lab in np.unique(labels):
            idx = np.flatnonzero(labels == lab)
            part = self._subset(idx)
            distinct = len(np.unique(part.translations, axis=0))
            c = (_pivot(part.rotations, part.translations, part.weights)
                 if pivot and distinct >= _MIN_MODE_PARTICLES else None)
            modes.append([idx, part, c, distinct, float(self.weights[idx].sum())])
        big = [m for m in modes if m[3] >= _MIN_MODE_PARTICLES]
        # A mode too small for a covariance (or pivot) of its own borrows the heaviest big
        # mode's pivot, and the big modes' covariances (mass-weighted) taken at their pivots.
        default_pivot = max(big, key=lambda m: m[4])[2] if big and pivot else np.zeros(3)
        label = np.empty(len(self), dtype=np.int64)
        chol, log_norm, centres, pivots, covs = [], [], [], [], []
        for j, (idx, part, c, _, _) in enumerate(modes):
            c = default_pivot if c is None else c
            shifted = PoseDistribution(part.rotations, part.translations + part.rotations @ c,
                                       part.weights)
            R, t, cov = shifted.mean_and_covariance()
            label[idx] = j
            centres.append((R, t))
            pivots.append(c)
            covs.append(cov)
        if big:
            pooled = sum(m[4] * covs[j] for j, m in enumerate(modes) if m[3] >= _MIN_MODE_PARTICLES) \
                / sum(m[4] for m in big)
        else:
            pooled = PoseDistribution(self.rotations, self.translations + self.rotations @ default_pivot,
                                      self.weights).mean_and_covariance()[2]
        for j, (_, part, _, distinct, _) in enumerate(modes):
            L, ln = _gaussian_kernel(covs[j] if distinct >= _MIN_MODE_PARTICLES else pooled,
                                     part._kernel_count())
            chol.append(L)
            log_norm.append(ln)
        return _ModeKernels(label, np.stack(chol), np.asarray(log_norm), np.stack(pivots), centres)

    def _log_density_many(self, R: NDArray[np.float64], t: NDArray[np.float64],
                          kernels: _ModeKernels, chunk: int = 256) -> NDArray[np.float64]:
        """Kernel log-density at ``m`` poses ``R`` (m, 3, 3), ``t`` (m, 3)."""
        out = np.empty(len(R))
        # Each particle's log-weight plus its kernel's log-normaliser.
        logw = np.log(self.weights) + kernels.log_norm[kernels.label]
        groups = [np.flatnonzero(kernels.label == j) for j in range(len(kernels.chol))]
        for s in range(0, len(R), chunk):
            Rq, tq = R[s:s + chunk], t[s:s + chunk]
            # rel[q, n] = R_n^T R_q: the query in the chart around each particle.
            rel = np.einsum("nji,qjk->qnik", self.rotations, Rq).reshape(-1, 3, 3)
            rv = Rotation.from_matrix(rel).as_rotvec().reshape(len(Rq), len(self), 3)
            d2 = np.empty((len(Rq), len(self)))
            for j, idx in enumerate(groups):
                c = kernels.pivots[j]
                dt = (tq + Rq @ c)[:, None, :] - (self.translations[idx] + self.rotations[idx] @ c)[None]
                X = np.concatenate([rv[:, idx], dt], axis=2)
                z = np.linalg.solve(kernels.chol[j], X.reshape(-1, 6).T)
                d2[:, idx] = np.sum(z * z, axis=0).reshape(len(Rq), len(idx))
            out[s:s + chunk] = logsumexp(logw[None] - 0.5 * d2, axis=1)
        return out

    def log_density(self, R: ArrayLike, t: ArrayLike) -> float:
        """Log-density of one pose under a Gaussian kernel density of the particles.

        Each particle carries a Gaussian in the chart around itself whose covariance is that of
        its mode (:meth:`modes`): ``h_m^2 C_m``, with ``C_m`` the weighted tangent covariance of
        the mode's particles and ``h_m`` Scott's factor ``n_m^(-1/10)``, ``n_m`` the mode's ESS
        (its weights renormalised) or, if fewer, its number of distinct particles (resampling
        repeats them). A mode with fewer than 12 distinct particles has no covariance of its
        own and takes the mass-weighted mean of the other modes' (if none has one, the
        covariance of all the particles). One covariance for the whole set, as a plain KDE
        has, would span the gaps between the modes (an arc and a flip) and smooth every mode
        down to nothing; per mode, a mode's density is the mode's own KDE times its mass.

        The chart's translation part is that of the mode's pivot ``c`` (object frame), the
        point whose position ``R c + t`` varies least over the mode (weighted least squares):
        ``x = (log(R_i^T R), (t + R c) - (t_i + R_i c))``. A mug turning about its axis (a
        hidden handle's arc) then moves along one straight direction of the chart instead of
        sweeping the origin's translation round a curve that a single covariance smears across.
        The shift ``t -> t + R c`` has unit Jacobian, so the density is unchanged in meaning.
        Against the exact normalised target at held-out draws of the importance sampler
        (``examples/benchmarks/bench_samplers.py --seeds 0 1 2 --kde-check``, YCB-Video 0000's mug, frames
        1-5): mean |error| 1.53-1.89 nats with one covariance for all the particles, 0.73-0.91
        per mode, 0.70-0.83 per mode with the pivot (the KDE's smoothing still biases it low,
        by 0.4-0.6 nats on average); on the demo (one mode) 0.64-0.84 for all three.

        The density is per unit of rotation vector (rad^3) and metre^3; the exp-map Jacobian is
        ignored, which is exact to O(h^2 |omega|^2) for kernels a few degrees wide.
        """
        R, t = _check_query(R, t)
        return float(self._log_density_many(R[None], t[None], self._mode_kernels())[0])

    def credible_level(self, R: ArrayLike, t: ArrayLike, *, max_particles: int = 2000,
                       rng: np.random.Generator | int | None = 0) -> float:
        """Smallest highest-density credible level whose region contains the pose ``(R, t)``.

        The mass of the particles whose kernel density (the per-mode kernels of
        :meth:`log_density`) exceeds the density at ``(R, t)``: the pose lies inside the
        ``alpha`` highest-density region iff the level is ``<= alpha``. For a calibrated
        distribution the level of the true pose is uniform on [0, 1]. The density at each
        particle leaves its own kernel out. Above ``max_particles`` the kernel density and the
        mass are taken over a systematic resampling of that size (whose repeated particles make
        the level slightly low).

        Parameters
        ----------
        R : (3, 3) array_like
        t : (3,) array_like
            Metres, in the frame of the particles.
        max_particles : int
        rng : numpy Generator, int or None
            For the resampling.

        Returns
        -------
        float
            In [0, 1].
        """
        R, t = _check_query(R, t)
        if int(max_particles) < 1:
            raise ValueError(f"Expected `max_particles` >= 1, got {max_particles}.")
        sub = self if len(self) <= max_particles else self.resample(int(max_particles), rng=rng)
        kern = sub._mode_kernels()
        logw = np.log(sub.weights)
        at_pose = np.full(len(kern.chol), -np.inf)
        at_particles = np.full((len(kern.chol), len(sub)), -np.inf)
        for j, (R0, t0) in enumerate(kern.centres):
            # Mode j's kernels in one chart around its mean (rather than one per particle, as
            # in log_density): O(n) rotation logarithms, then a Euclidean kernel sum.
            idx = np.flatnonzero(kern.label == j)
            L, c = kern.chol[j], kern.pivots[j]
            X = np.hstack([Rotation.from_matrix(np.einsum("ji,njk->nik", R0, sub.rotations)).as_rotvec(),
                           sub.translations + sub.rotations @ c - t0])
            Z = np.linalg.solve(L, X.T).T
            zq = np.linalg.solve(L, np.hstack([Rotation.from_matrix(R0.T @ R).as_rotvec(), t + R @ c - t0]))
            lw = logw[idx] + kern.log_norm[j]
            at_pose[j] = logsumexp(lw - 0.5 * np.sum((Z[idx] - zq) ** 2, axis=1))
            for s in range(0, len(sub), 512):
                d2 = np.sum((Z[s:s + 512, None, :] - Z[None, idx, :]) ** 2, axis=2)
                at_particles[j, s:s + 512] = logsumexp(lw[None] - 0.5 * d2, axis=1)
        at_pose = logsumexp(at_pose)
        at_particles = logsumexp(at_particles, axis=0)
        # Leave each particle's own kernel out: with it, the density at a particle is biased
        # up by w_i K(0), which dominates in the tails.
        self_term = logw + kern.log_norm[kern.label]
        with np.errstate(divide="ignore", invalid="ignore"):
            loo = at_particles + np.log1p(-np.exp(np.minimum(self_term - at_particles, 0.0))) \
                - np.log1p(-np.minimum(sub.weights, 1.0 - 1e-12))
        return float(min(np.sum(sub.weights[loo > at_pose]), 1.0))

    def save(self, path: str | Path) -> None:
        """Write ``rotations``, ``translations``, ``weights`` (and raw ``log_weights``) to ``.npz``."""
        arrays = dict(
            rotations=self.rotations, translations=self.translations, weights=self.weights
        )
        if self.log_weights is not None:
            arrays["log_weights"] = self.log_weights
        from certpose.io.output import atomic_path

        # np.savez adds ".npz" to a name without it: write the name it will have.
        target = Path(path) if str(path).endswith(".npz") else Path(f"{path}.npz")
        with atomic_path(target) as tmp, tmp.open("wb") as fh:
            np.savez(fh, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> PoseDistribution:
        """Read a distribution written by :meth:`save`.

        Raises
        ------
        ValueError
            The file is missing, not a ``.npz`` archive (e.g. truncated), lacks a key, or holds
            invalid particles.
        """
        import zipfile

        try:
            # np.load returns a bare array for .npy files and leaves a cut archive open.
            if not Path(path).is_file():
                raise ValueError("no such file")
            if not zipfile.is_zipfile(path):
                raise ValueError("not a .npz archive (truncated, or another format)")
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ValueError(f"Cannot read particle file {str(path)!r}: {exc}") from exc
        with data:
            missing = {"rotations", "translations", "weights"} - set(data.files)
            if missing:
                raise ValueError(f"Particle file {str(path)!r} lacks {sorted(missing)}.")
            lw = data["log_weights"] if "log_weights" in data.files else None
            return cls(data["rotations"], data["translations"], data["weights"], log_weights=lw)
