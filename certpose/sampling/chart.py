"""The one 6-D parametrisation of poses shared by the baselines and the initialisers.

Around a reference pose ``T_ref = (R_ref, t_ref)`` (``T_camera_object`` or ``T_scene_object``),
a pose ``(R, t)`` has chart coordinates

    xi = (log(R_ref^T R), t - t_ref)        (6,): radians, then metres

the rotation vector of the object-frame rotation from the reference followed by the translation
offset in the reference's parent frame (camera or scene). It is the chart of
:meth:`certpose.sampling.PoseDistribution.tangent` and of the importance sampler's proposal, and
the inverse is ``R = R_ref exp([xi_0:3]_x)``, ``t = t_ref + xi_3:6``.

(gtsam's ``Pose3`` tangent differs in the translation: body frame, ``R_ref^T (t - t_ref)`` to
first order; :func:`certpose.sampling.initialisers.gtsam_priors` converts.)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

__all__ = ["check_pose", "from_chart", "to_chart"]


def check_pose(T: ArrayLike, *, name: str = "T_ref") -> NDArray[np.float64]:
    """Validate one (4, 4) rigid transform; returns it as float64."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"Expected `{name}` to have shape (4, 4), got {T.shape}.")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"`{name}` contains NaN or infinite values.")
    R = T[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > 1e-6 or np.linalg.det(R) < 0:
        raise ValueError(f"`{name}`'s rotation block is not a rotation (|R^T R - I| = {err:.2e}, "
                         f"det = {np.linalg.det(R):.3f}).")
    return T


def to_chart(rotations: ArrayLike, translations: ArrayLike, T_ref: ArrayLike) -> NDArray[np.float64]:
    """(n, 6) chart coordinates of poses ``rotations`` (n, 3, 3), ``translations`` (n, 3)."""
    T_ref = check_pose(T_ref)
    R = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    t = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
    rv = Rotation.from_matrix(np.einsum("ji,njk->nik", T_ref[:3, :3], R)).as_rotvec()
    return np.hstack([rv, t - T_ref[:3, 3]])


def from_chart(xi: ArrayLike, T_ref: ArrayLike) -> NDArray[np.float64]:
    """(n, 4, 4) poses of chart coordinates ``xi`` (n, 6) or (6,)."""
    T_ref = check_pose(T_ref)
    x = np.asarray(xi, dtype=np.float64)
    if x.ndim == 1:
        x = x[None]
    if x.ndim != 2 or x.shape[1] != 6:
        raise ValueError(f"Expected `xi` to have shape (n, 6), got {np.shape(xi)}.")
    if not np.all(np.isfinite(x)):
        raise ValueError("`xi` contains NaN or infinite values.")
    T = np.tile(np.eye(4), (len(x), 1, 1))
    T[:, :3, :3] = np.einsum("ij,njk->nik", T_ref[:3, :3], Rotation.from_rotvec(x[:, :3]).as_matrix())
    T[:, :3, 3] = T_ref[:3, 3] + x[:, 3:]
    return T
