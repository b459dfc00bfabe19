"""SO(3) helpers: hat, Exp, Log, quaternion conversion.

Conventions (tangent ``ω`` in rad, right perturbation): ``docs/conventions.md``.
Rotations are 3x3 float64 arrays; batches are (N, 3, 3).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from metricslam.errors import GeometryError


def hat(omega: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix of a 3-vector: ``hat(a) @ b == cross(a, b)``. (3,) -> (3, 3)."""
    wx, wy, wz = _vec3(omega)
    return np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])


def vee(omega_hat: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat`. (3, 3) -> (3,)."""
    m = np.asarray(omega_hat, dtype=float)
    return np.array([m[2, 1], m[0, 2], m[1, 0]])


def exp(omega: np.ndarray) -> np.ndarray:
    """Rotation vector (rad, (3,)) -> rotation matrix (3, 3)."""
    return Rotation.from_rotvec(_vec3(omega)).as_matrix()


def log(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> rotation vector (3,) with norm in [0, π]."""
    return Rotation.from_matrix(check_rotation(R)).as_rotvec()


def angle(R: np.ndarray) -> float:
    """Rotation angle in rad, in [0, π], computed robustly from the trace (like the KITTI devkit)."""
    R = np.asarray(R, dtype=float)
    c = 0.5 * (np.trace(R) - 1.0)
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def from_quat_xyzw(q_xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternion ``[x, y, z, w]`` -> rotation matrix. Normalizes; zero norm raises."""
    q = np.asarray(q_xyzw, dtype=float).reshape(4)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-12:
        raise GeometryError(f"quaternion {q.tolist()} has zero or non-finite norm")
    return Rotation.from_quat(q / n).as_matrix()


def to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion ``[x, y, z, w]`` with w >= 0."""
    q = Rotation.from_matrix(check_rotation(R)).as_quat()
    return q if q[3] >= 0 else -q


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius) to a 3x3 matrix, via SVD."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def check_rotation(R: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Return ``R`` as float64 (3, 3) or raise :class:`GeometryError` if it is not a rotation."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise GeometryError(f"expected a finite 3x3 rotation matrix, got shape {R.shape}")
    if np.abs(R @ R.T - np.eye(3)).max() > tol or np.linalg.det(R) < 0:
        raise GeometryError("matrix is not a rotation (R·Rᵀ != I or det < 0); re-orthonormalize it")
    return R


def _vec3(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    if v.shape != (3,):
        raise GeometryError(f"expected a 3-vector, got shape {v.shape}")
    return v
