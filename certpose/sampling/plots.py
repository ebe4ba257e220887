"""Marginals of a :class:`~certpose.sampling.PoseDistribution` and their plot (the paper's fig. 1).

Marginals: roll, pitch, yaw of ``R_camera_object`` (``R = Rz(yaw) Ry(pitch) Rx(roll)``, scipy's
intrinsic ``"ZYX"``), the translation ``x, y, z`` (camera frame), and the rotation about a
given object axis relative to a reference pose (the twist angle of ``R_ref^T R`` about the axis,
e.g. a mug's handle angle about its own axis). Each is a weighted Gaussian KDE
(``scipy.stats.gaussian_kde``, Scott's rule on the weights' effective size). Angles that wrap
(roll, yaw, the axis angle) are centred on their circular mean and the kernel is tiled over
three turns with the bandwidth of the centred data, so mass near +-180 deg is not split.

matplotlib is imported only by :func:`plot_marginals` (the Agg canvas: files, no display).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from certpose.sampling.chart import check_pose
from certpose.sampling.distribution import PoseDistribution

__all__ = ["Marginal", "axis_angles", "euler_angles", "marginal_kde", "marginals", "plot_marginals"]

log = logging.getLogger(__name__)

_TWO_PI = 2.0 * math.pi


def _wrap(a: NDArray[np.float64]) -> NDArray[np.float64]:
    return (np.asarray(a) + math.pi) % _TWO_PI - math.pi


def _check_dist(dist: object) -> PoseDistribution:
    if not isinstance(dist, PoseDistribution):
        raise TypeError(f"Expected `dist` to be a PoseDistribution, got {type(dist).__name__}.")
    return dist


def _check_axis(axis: ArrayLike) -> NDArray[np.float64]:
    a = np.asarray(axis, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"Expected `axis` to have shape (3,), got {a.shape}.")
    n = float(np.linalg.norm(a))
    if not (math.isfinite(n) and n > 1e-12):
        raise ValueError(f"Expected `axis` to be a finite non-zero vector, got {a.tolist()}.")
    return a / n


def euler_angles(rotations: ArrayLike) -> NDArray[np.float64]:
    """(n, 3) roll, pitch, yaw (rad) of rotations (n, 3, 3): ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    R = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # gimbal lock: scipy still answers
            return Rotation.from_matrix(R).as_euler("ZYX")[:, ::-1].copy()


def axis_angles(rotations: ArrayLike, axis: ArrayLike, T_ref: ArrayLike) -> NDArray[np.float64]:
    """(n,) rotation (rad, in [-pi, pi)) about the object-frame ``axis`` from the reference.

    The twist angle of the swing-twist decomposition of ``R_ref^T R``: ``2 atan2(q_v . a, q_w)``
    for its quaternion ``(q_v, q_w)``; exact for rotations about ``axis``, and for others it
    ignores the tilt of the axis.
    """
    a = _check_axis(axis)
    T_ref = check_pose(T_ref)
    R = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    q = Rotation.from_matrix(np.einsum("ji,njk->nik", T_ref[:3, :3], R)).as_quat()  # x, y, z, w
    return _wrap(2.0 * np.arctan2(q[:, :3] @ a, q[:, 3]))


def marginal_kde(
    values: ArrayLike,
    weights: ArrayLike,
    grid: ArrayLike,
    *,
    periodic: bool = False,
) -> NDArray[np.float64]:
    """Weighted Gaussian KDE of 1-D ``values`` evaluated on ``grid`` (same units).

    With ``periodic`` the values are angles (rad) and the density is that of the circle
    (integrates to 1 over any interval of length ``2 pi``); ``grid`` may be any angles.
    """
    from scipy.stats import gaussian_kde

    v = np.asarray(values, dtype=np.float64).reshape(-1)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    g = np.asarray(grid, dtype=np.float64).reshape(-1)
    if v.size == 0:
        raise ValueError("Expected a non-empty set of `values`, got 0.")
    if w.shape != v.shape:
        raise ValueError(f"Expected `weights` to have shape {v.shape}, got {w.shape}.")
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(w))):
        raise ValueError("`values` or `weights` contains NaN or infinite values.")
    if np.any(w < 0) or w.sum() <= 0:
        raise ValueError("`weights` must be non-negative with a positive sum.")
    w = w / w.sum()
    mu = 0.0
    if periodic:
        mu = float(np.arctan2(w @ np.sin(v), w @ np.cos(v)))
        v = _wrap(v - mu)
    m = float(w @ v)
    var = float(w @ (v - m) ** 2)
    ess = 1.0 / float(np.sum(w**2))
    if var < 1e-18 or ess < 2.0:
        # No spread to fit a bandwidth to: a narrow Gaussian at the (single) value.
        from scipy.stats import norm

        x = _wrap(g - mu) if periodic else g
        scale = 1e-3 if periodic else max(1e-6, 1e-3 * abs(m))
        return norm.pdf(x, loc=m, scale=scale)
    kde = gaussian_kde(v, weights=w)
    if not periodic:
        return kde(g)
    h2 = float(kde.covariance[0, 0])
    tiled = gaussian_kde(np.concatenate([v - _TWO_PI, v, v + _TWO_PI]),
                         weights=np.concatenate([w, w, w]) / 3.0)
    data_var = float(tiled.covariance[0, 0]) / tiled.factor**2
    tiled.set_bandwidth(bw_method=math.sqrt(h2 / data_var))
    return 3.0 * tiled(_wrap(g - mu))


@dataclass(frozen=True)
class Marginal:
    """One marginal: ``density`` on ``grid`` (display units), and the truth when known.

    Attributes
    ----------
    name : str
    unit : str
        ``"deg"`` or ``"cm"``.
    grid : (G,) ndarray
    density : (G,) ndarray
        Per display unit.
    truth : float or None
    mean : float
        Weighted (circular, for angles) mean.
    """

    name: str
    unit: str
    grid: NDArray[np.float64]
    density: NDArray[np.float64]
    truth: float | None
    mean: float


def _marginal(name: str, v: NDArray, w: NDArray, truth: float | None, *, angle: bool,
              n_grid: int) -> Marginal:
    """Angles in rad (displayed in deg, grid around the circular mean), lengths in m (cm)."""
    if angle:
        mu = float(np.arctan2(w @ np.sin(v), w @ np.cos(v)))
        c = _wrap(v - mu)
        sd = math.sqrt(max(float(w @ (c - w @ c) ** 2), 1e-10))
        pad = 0.5 * sd + 0.02  # the kernels' tails
        lo, hi = max(c.min() - pad, -math.pi), min(c.max() + pad, math.pi)
        if truth is not None:
            tc = float(_wrap(truth - mu))
            lo, hi = min(lo, tc - 0.02), max(hi, tc + 0.02)
            truth = math.degrees(mu + tc)
        g = np.linspace(lo, hi, n_grid)
        dens = marginal_kde(v, w, mu + g, periodic=True)
        return Marginal(name, "deg", np.degrees(mu + g), dens * math.pi / 180.0, truth,
                        math.degrees(mu))
    m = float(w @ v)
    sd = math.sqrt(max(float(w @ (v - m) ** 2), 1e-14))
    lo, hi = v.min() - sd, v.max() + sd
    if truth is not None:
        lo, hi = min(lo, truth - sd), max(hi, truth + sd)
        truth = 100.0 * truth
    g = np.linspace(lo, hi, n_grid)
    return Marginal(name, "cm", 100.0 * g, marginal_kde(v, w, g) / 100.0, truth, 100.0 * m)


def marginals(
    dist: PoseDistribution,
    *,
    axis: ArrayLike | None = None,
    T_ref: ArrayLike | None = None,
    T_gt: ArrayLike | None = None,
    n_grid: int = 256,
    max_particles: int = 5000,
    rng: np.random.Generator | int | None = 0,
) -> list[Marginal]:
    """Roll, pitch, yaw, x, y, z (and, with ``axis``, the rotation about it) of ``dist``.

    Parameters
    ----------
    dist : PoseDistribution
        Particles as ``T_camera_object``.
    axis : (3,) array_like, optional
        Object-frame axis (e.g. a mug's ``(0, 0, 1)``) for the rotation-about-axis marginal.
    T_ref : (4, 4) array_like, optional
        Reference of the axis angle (default: ``T_gt`` when given, else the heaviest mode).
    T_gt : (4, 4) array_like, optional
        Ground truth, marked on every marginal.
    n_grid : int
        Grid points per marginal.
    max_particles : int
        Larger distributions are resampled to this many particles (the KDE costs
        particles x grid points).
    """
    d = _check_dist(dist)
    if int(n_grid) < 2:
        raise ValueError(f"Expected `n_grid` >= 2, got {n_grid}.")
    if int(max_particles) < 1:
        raise ValueError(f"Expected `max_particles` >= 1, got {max_particles}.")
    gt = None if T_gt is None else check_pose(T_gt, name="T_gt")
    if len(d) > max_particles:
        d = d.resample(int(max_particles), rng=rng)
    w = d.weights
    eul = euler_angles(d.rotations)
    eul_gt = None if gt is None else euler_angles(gt[:3, :3][None])[0]
    out = []
    for j, name in enumerate(("roll", "pitch", "yaw")):
        out.append(_marginal(name, eul[:, j], w, None if gt is None else float(eul_gt[j]),
                             angle=True, n_grid=int(n_grid)))
    for j, name in enumerate("xyz"):
        out.append(_marginal(name, d.translations[:, j], w,
                             None if gt is None else float(gt[j, 3]), angle=False, n_grid=int(n_grid)))
    if axis is not None:
        ref = T_ref if T_ref is not None else (gt if gt is not None else _check_dist(dist).modes()[0].T)
        a = axis_angles(d.rotations, axis, ref)
        truth = None if gt is None else float(axis_angles(gt[:3, :3][None], axis, ref)[0])
        ax = _check_axis(axis)
        out.append(_marginal(f"rotation about axis ({ax[0]:.2g}, {ax[1]:.2g}, {ax[2]:.2g})", a, w,
                             truth, angle=True, n_grid=int(n_grid)))
    return out


def plot_marginals(
    dist: PoseDistribution,
    path: str | Path,
    *,
    axis: ArrayLike | None = None,
    T_ref: ArrayLike | None = None,
    T_gt: ArrayLike | None = None,
    title: str | None = None,
    notes: list[str] | None = None,
    size: tuple[float, float] = (12.0, 6.0),
    dpi: int = 100,
    arcs: Sequence[tuple[float, float]] | None = None,
    arcs_label: str = "hidden arc",
) -> Path:
    """Write the marginals of :func:`marginals` as a PNG (``size`` inches at ``dpi``).

    Rotation marginals on the top row, translation on the bottom; the ground truth (when
    given) as a red line; with ``axis``, a text panel lists ``notes`` (e.g. the sampler's ESS),
    the particle count and the modes' masses, and ``arcs`` (``(start, end)`` pairs, degrees of
    rotation about ``axis`` from the same reference as the panel, e.g. a
    :class:`~certpose.model.arc.FreeSpaceArc`'s ``arcs``) are shaded on the axis panel with
    ``arcs_label``. Returns the path written.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    p = Path(path)
    if not p.parent.is_dir():
        raise OSError(f"cannot write plot '{p}': folder '{p.parent}' does not exist.")
    if len(size) != 2 or not all(math.isfinite(s) and s > 0 for s in size):
        raise ValueError(f"Expected `size` to be two positive numbers (inches), got {size}.")
    spans = []
    for k, arc in enumerate(arcs or ()):
        lo, hi = (float(v) for v in arc)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise ValueError(f"Expected `arcs[{k}]` to be finite degrees (start <= end), got {arc}.")
        # A run across +-180 deg ends above 180: shade both of its pieces.
        spans += [(lo, min(hi, 180.0))] + ([(-180.0, hi - 360.0)] if hi > 180.0 else [])
    if spans and axis is None:
        raise ValueError("`arcs` are angles about `axis`; give `axis` too.")
    ms = marginals(dist, axis=axis, T_ref=T_ref, T_gt=T_gt)
    ncol = 4  # the fourth column: the turn about the axis (if any) above the diagnostics
    fig = Figure(figsize=size, dpi=int(dpi))
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, ncol, squeeze=False)
    slots = [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2)] + ([(0, 3)] if axis is not None else [])
    for m, (r, c) in zip(ms, slots, strict=True):
        ax = axes[r, c]
        ax.fill_between(m.grid, m.density, alpha=0.3)
        ax.plot(m.grid, m.density, lw=1.2)
        if m.truth is not None:
            ax.axvline(m.truth, color="red", lw=1.2, label="ground truth")
        if (r, c) == (0, 3):
            for k, (lo, hi) in enumerate(spans):
                ax.axvspan(lo, hi, color="green", alpha=0.15, lw=0, label=arcs_label if k == 0 else None)
            if spans:
                ax.legend(loc="upper right", fontsize=8)
        ax.set_xlabel(f"{m.name} ({m.unit})")
        ax.set_yticks([])
    if T_gt is not None:
        axes[0, 0].legend(loc="upper right", fontsize=8)
    if axis is None:
        axes[0, 3].axis("off")
    # The diagnostics, with or without an axis.
    info = axes[1, 3]
    info.axis("off")
    d = _check_dist(dist)
    lines = list(notes or []) + [f"{len(d)} particles (ESS {d.ess:.0f})"]
    if d.log_weights is not None:
        try:
            lines.append(f"Pareto-k {d.pareto_k():.2f}")
        except Exception:  # noqa: BLE001 - a diagnostic for the caption only
            pass
    lines += [f"mode {k}: mass {mo.mass:.2f}" for k, mo in enumerate(d.modes()[:4]) if mo.mass >= 0.005]
    info.text(0.0, 1.0, "\n".join(lines), va="top", family="monospace", fontsize=9)
    fig.suptitle(title or "pose distribution: marginals (KDE)")
    fig.tight_layout()
    from certpose.io.output import atomic_path

    with atomic_path(p) as tmp:
        fig.savefig(tmp, dpi=int(dpi), format=p.suffix.lstrip(".") or None)
    log.info("wrote %s", p)
    return p
