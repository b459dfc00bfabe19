"""SE(3) helpers on 4x4 homogeneous float64 arrays.

``T_a_b`` maps points from frame ``b`` to frame ``a``. Tangent order ``[ω, v]`` (rotation first,
as gtsam), right perturbation. See ``docs/conventions.md``.
"""

from __future__ import annotations

import numpy as np

from metricslam.errors import GeometryError
from metricslam.geometry import so3
from metricslam.geometry._jacobian import left_jacobian_sim


def from_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build ``T`` (4, 4) from rotation (3, 3) and translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def check(T: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Return ``T`` as float64 (4, 4) or raise :class:`GeometryError` if it is not in SE(3)."""
    T = np.asarray(T, dtype=float)
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4):
        raise GeometryError(f"expected a 4x4 (or 3x4) rigid transform, got shape {T.shape}")
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > tol:
        raise GeometryError("last row of a rigid transform must be [0, 0, 0, 1]")
    so3.check_rotation(T[:3, :3], tol)
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """``T_b_a`` from ``T_a_b`` (closed form, no matrix inverse)."""
    R, t = T[:3, :3], T[:3, 3]
    return from_rt(R.T, -R.T @ t)


def compose(*Ts: np.ndarray) -> np.ndarray:
    """Left-to-right product ``T1 @ T2 @ ...``."""
    out = np.eye(4)
    for T in Ts:
        out = out @ T
    return out


def exp(xi: np.ndarray) -> np.ndarray:
    """``[ω, v]`` (6,) -> ``T`` (4, 4)."""
    xi = np.asarray(xi, dtype=float).reshape(6)
    omega, v = xi[:3], xi[3:]
    return from_rt(so3.exp(omega), left_jacobian_sim(omega, 0.0) @ v)


def log(T: np.ndarray) -> np.ndarray:
    """``T`` (4, 4) -> ``[ω, v]`` (6,)."""
    T = check(T)
    omega = so3.log(T[:3, :3])
    v = np.linalg.solve(left_jacobian_sim(omega, 0.0), T[:3, 3])
    return np.concatenate([omega, v])


def retract(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Right perturbation ``T @ Exp(ξ)``."""
    return T @ exp(xi)


def local(T1: np.ndarray, T2: np.ndarray) -> np.ndarray:
    """``Log(T1⁻¹ T2)``: the right-perturbation that takes ``T1`` to ``T2``."""
    return log(inverse(T1) @ T2)


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint for tangent order ``[ω, v]``: ``T Exp(ξ) T⁻¹ = Exp(Ad_T ξ)``."""
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = so3.hat(t) @ R
    return Ad


def transform_points(T_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Apply ``T_a_b`` to points (N, 3) (or (3,)) expressed in ``b``; returns points in ``a``."""
    p = np.asarray(p_b, dtype=float)
    return p @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def from_3x4_rows(values: np.ndarray) -> np.ndarray:
    """KITTI line (12 values, row-major 3x4) -> (4, 4)."""
    v = np.asarray(values, dtype=float).reshape(3, 4)
    return np.vstack([v, [0.0, 0.0, 0.0, 1.0]])
