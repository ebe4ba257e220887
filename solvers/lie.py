"""SO(3) and SE(3) helpers on 3x3 rotation matrices and 4x4 homogeneous transforms.

Conventions: ``T_a_b`` maps points expressed in frame ``b`` into frame ``a``; points are
``(N, 3)`` rows, so ``transform_points(T_a_b, p_b) = p_b @ R.T + t``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from solvers.validation import as_float_array, check_rotation, check_transform

__all__ = [
    "so3_exp",
    "so3_exp_batch",
    "so3_log",
    "se3_exp",
    "se3_log",
    "make_transform",
    "invert_transform",
    "transform_points",
    "project_to_so3",
    "rotation_angle_deg",
    "rotation_error_deg",
    "translation_error",
]

# Rotation vectors, quaternions and random rotations: scipy.spatial.transform.Rotation.

_SMALL = 1e-10

# Orthonormality tolerance of rotation inputs: float32 rotations (file ground truth) pass.
_ROTATION_ATOL = 1e-5


def _vector(value: ArrayLike, name: str, size: int) -> NDArray[np.float64]:
    """A finite float64 vector of shape ``(size,)``."""
    arr = as_float_array(value, name, allow_bool=False)
    if arr.shape != (size,):
        raise ValueError(f"Expected `{name}` to have shape ({size},), got {arr.shape}.")
    if not np.isfinite(arr).all():
        raise ValueError(f"`{name}` contains NaN or inf values.")
    return arr


def _rotations(value: ArrayLike, name: str) -> NDArray[np.float64]:
    """Finite rotation matrices of shape ``(..., 3, 3)`` (orthonormal, determinant +1)."""
    R = as_float_array(value, name, allow_bool=False, copy=False)  # read only
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"Expected `{name}` to have shape (..., 3, 3), got {R.shape}.")
    if R.size == 0:
        return R
    err, det = _orthonormality(R)
    if not (err <= _ROTATION_ATOL and det > 0):  # NaN fails both
        if not np.isfinite(R).all():
            raise ValueError(f"`{name}` contains NaN or inf values.")
        raise ValueError(
            f"`{name}` is not a rotation matrix (orthonormal with det +1): "
            f"max |R^T R - I| = {err:.3g}, smallest det = {det:.3g}; project it "
            "with `solvers.lie.project_to_so3` first.")
    return R


def _orthonormality(R: NDArray[np.float64]) -> tuple[float, float]:
    """``max |R^T R - I|`` and the smallest determinant over a stack of 3x3 matrices."""
    with np.errstate(invalid="ignore", over="ignore"):  # NaN/inf: the caller says which
        if R.ndim == 2 or R.size <= 16 * 9:  # few: numpy's per-matrix routines are cheapest
            err = float(np.abs(np.matmul(np.swapaxes(R, -1, -2), R) - np.eye(3)).max())
            return err, float(np.min(np.linalg.det(R)))
        # Many: entry by entry over the whole stack, in place (numpy's stacked matmul and det
        # loop over the 3x3 matrices one at a time: 8x the time of so3_log itself at 10^4).
        F = np.ascontiguousarray(R.reshape(-1, 9).T)  # F[3 i + j]: entry (i, j) of each
        acc, tmp = np.empty(F.shape[1]), np.empty(F.shape[1])
        err = 0.0
        for j, k in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)):  # columns' dot products
            np.multiply(F[j], F[k], out=acc)
            acc += np.multiply(F[3 + j], F[3 + k], out=tmp)
            acc += np.multiply(F[6 + j], F[6 + k], out=tmp)
            if j == k:
                acc -= 1.0
            err = max(err, float(np.abs(acc, out=acc).max()))
        a, b, c, d, e, f, g, h, i = F
        det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
        return err, float(det.min())


def so3_exp(omega: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix of the rotation vector ``omega`` (3,), radians (``Rotation.from_rotvec``)."""
    from scipy.spatial.transform import Rotation  # scipy.spatial: not on `import solvers`

    return Rotation.from_rotvec(_vector(omega, "omega", 3)).as_matrix()


def so3_exp_batch(omegas: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrices (n, 3, 3) of the rotation vectors ``omegas`` (n, 3), radians: the same
    numbers as ``Rotation.from_rotvec(omegas).as_matrix()``, compiled
    (:func:`solvers._linalg_kernels.rotvec_matrices`; for the many small batches of a local
    search, where scipy's per-call overhead is most of the time)."""
    from solvers.jit import compiled

    v = as_float_array(omegas, "omegas", allow_bool=False)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"Expected `omegas` to have shape (n, 3), got {v.shape}.")
    if not np.isfinite(v).all():
        raise ValueError("`omegas` contains NaN or inf values.")
    v = np.ascontiguousarray(v)
    return compiled("solvers._linalg_kernels").rotvec_matrices(v)


def so3_log(R: ArrayLike, *, check: bool = True) -> NDArray[np.float64]:
    """Rotation vectors (..., 3), radians, of rotation matrices ``R`` (..., 3, 3), vectorised.

    The inverse of :func:`so3_exp`, with angles in [0, pi]. The same values as scipy's
    ``Rotation.from_matrix(R).as_rotvec()`` without its per-call cost, which dominated the
    importance sampler's mixture density (many small batches). Within 0.1 rad of a half turn,
    where ``theta / (2 sin theta)`` loses its precision, Shepperd's quaternion is used instead.

    ``check=False`` skips the test that ``R`` holds rotations (about a third of the time at
    10^4 matrices), for callers whose matrices are rotations by construction (products of
    checked rotations); the shape is checked either way.

    Raises
    ------
    ValueError
        ``R`` is not a stack of rotation matrices (shape, NaN/inf, orthonormality, det +1).
    """
    if check:
        R = _rotations(R, "R")
    else:
        R = np.asarray(R, dtype=np.float64)
        if R.ndim < 2 or R.shape[-2:] != (3, 3):
            raise ValueError(f"Expected `R` to have shape (..., 3, 3), got {R.shape}.")
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    cos = np.clip((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    small = theta < 1e-4
    factor = np.where(small, 0.5 + theta**2 / 12.0,
                      theta / (2.0 * np.where(small, 1.0, np.sin(theta))))
    w = v * factor[..., None]
    near_pi = theta > np.pi - 0.1
    if np.any(near_pi):
        w[near_pi] = _so3_log_near_pi(R[near_pi])
    return w


def _so3_log_near_pi(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation vectors of rotations ``R`` (n, 3, 3) near a half turn (Shepperd's quaternion
    from the largest diagonal entry; the angle from ``atan2``)."""
    n = len(R)
    d = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], axis=1)
    i = np.argmax(d, axis=1)
    j, k = (i + 1) % 3, (i + 2) % 3
    r = np.arange(n)
    q = np.empty((n, 4))  # (x, y, z, w)
    big = np.sqrt(np.maximum(1.0 + d[r, i] - d[r, j] - d[r, k], 1e-300)) / 2.0
    q[r, i] = big
    q[r, j] = (R[r, j, i] + R[r, i, j]) / (4.0 * big)
    q[r, k] = (R[r, k, i] + R[r, i, k]) / (4.0 * big)
    q[:, 3] = (R[r, k, j] - R[r, j, k]) / (4.0 * big)
    q *= np.where(q[:, 3] < 0, -1.0, 1.0)[:, None]
    v = np.linalg.norm(q[:, :3], axis=1)
    return q[:, :3] * (2.0 * np.arctan2(v, q[:, 3]) / v)[:, None]


def _left_jacobian(omega: NDArray[np.float64]) -> NDArray[np.float64]:
    theta2 = float(omega @ omega)
    x, y, z = omega
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    if theta2 < _SMALL:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    theta = np.sqrt(theta2)
    return (
        np.eye(3)
        + ((1 - np.cos(theta)) / theta2) * K
        + ((theta - np.sin(theta)) / (theta2 * theta)) * K @ K
    )


def se3_exp(xi: ArrayLike) -> NDArray[np.float64]:
    """4x4 transform of a twist ``xi = [rho, omega]`` (translation part first)."""
    xi = _vector(xi, "xi", 6)
    rho, omega = xi[:3], xi[3:]
    T = np.eye(4)
    T[:3, :3] = so3_exp(omega)
    T[:3, 3] = _left_jacobian(omega) @ rho
    return T


def se3_log(T: ArrayLike) -> NDArray[np.float64]:
    """Twist ``[rho, omega]`` of a 4x4 transform; the inverse of :func:`se3_exp`."""
    from scipy.spatial.transform import Rotation

    T = check_transform(T, "T", atol=_ROTATION_ATOL)
    omega = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    rho = np.linalg.solve(_left_jacobian(omega), T[:3, 3])
    return np.concatenate([rho, omega])


def make_transform(rotation: ArrayLike, translation: ArrayLike) -> NDArray[np.float64]:
    """Assemble a 4x4 homogeneous transform from ``R`` (3, 3) and ``t`` (3,).

    Raises
    ------
    ValueError
        ``rotation`` is not a rotation matrix or ``translation`` not a finite (3,) vector.
    """
    T = np.eye(4)
    T[:3, :3] = check_rotation(rotation, "rotation", atol=_ROTATION_ATOL)
    T[:3, 3] = _vector(translation, "translation", 3)
    return T


def invert_transform(T: ArrayLike) -> NDArray[np.float64]:
    """Inverse of a rigid 4x4 transform (``T_b_a`` from ``T_a_b``).

    Raises
    ------
    ValueError
        ``T`` is not a rigid transform (the transpose is then not the inverse).
    """
    T = check_transform(T, "T", atol=_ROTATION_ATOL)
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def transform_points(T: ArrayLike, points: ArrayLike) -> NDArray[np.float64]:
    """Apply ``T`` (4, 4), a rigid transform, to ``points`` (N, 3)."""
    T = check_transform(T, "T", atol=_ROTATION_ATOL)
    p = as_float_array(points, "points", allow_bool=False)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"Expected `points` to have shape (N, 3), got {p.shape}.")
    return p @ T[:3, :3].T + T[:3, 3]


def project_to_so3(M: ArrayLike) -> NDArray[np.float64]:
    """Closest rotation matrix to ``M`` (3, 3) in the Frobenius norm (SVD, det corrected).

    Raises
    ------
    ValueError
        ``M`` is not a finite (3, 3) matrix, or has rank below 2: then no rotation is closest
        (every rotation about the one remaining direction is as close; a zero matrix has no
        preferred rotation at all).
    """
    from solvers.procrustes import weighted_rotation

    A = as_float_array(M, "M", allow_bool=False)
    if A.shape != (3, 3):
        raise ValueError(f"Expected `M` to have shape (3, 3), got {A.shape}.")
    if not np.isfinite(A).all():
        raise ValueError("`M` contains NaN or inf values.")
    s = np.linalg.svd(A, compute_uv=False)
    if not s[1] > 1e-12 * s[0]:
        raise ValueError(
            f"`M` has rank below 2 (singular values {s[0]:.3g}, {s[1]:.3g}, {s[2]:.3g}): its "
            "closest rotation is not unique.")
    return weighted_rotation(A)


def rotation_angle_deg(R: ArrayLike) -> float:
    """Geodesic angle of the rotation ``R`` (3, 3) from the identity, in degrees."""
    R = _rotations(R, "R")
    if R.shape != (3, 3):
        raise ValueError(f"Expected `R` to have shape (3, 3), got {R.shape}.")
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def rotation_error_deg(R_est: ArrayLike, R_gt: ArrayLike) -> float:
    """Geodesic rotation error ``arccos((tr(R_gt^T R_est) - 1) / 2)`` in degrees.

    Raises
    ------
    ValueError
        Either argument is not a (3, 3) rotation matrix.
    """
    R_est = check_rotation(R_est, "R_est", atol=_ROTATION_ATOL)
    R_gt = check_rotation(R_gt, "R_gt", atol=_ROTATION_ATOL)
    return rotation_angle_deg(R_gt.T @ R_est)


def translation_error(t_est: ArrayLike, t_gt: ArrayLike) -> float:
    """Euclidean translation error between ``t_est`` and ``t_gt`` (3,), in their units."""
    return float(np.linalg.norm(_vector(t_est, "t_est", 3) - _vector(t_gt, "t_gt", 3)))
