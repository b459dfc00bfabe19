"""Sim(3) helpers on 4x4 float64 arrays ``S_a_b = [[s·R, t], [0, 1]]`` (``p_a = s·R·p_b + t``).

Tangent order ``[ω, u, λ]`` with ``s = e^λ`` (as gtsam), right perturbation.
gtsam's ``Similarity3(R, t_g, s)`` maps ``p → s·(R·p + t_g)``: convert with ``t_g = t / s``.
See ``docs/conventions.md``.
"""

from __future__ import annotations

import numpy as np

from metricslam.errors import GeometryError
from metricslam.geometry import so3
from metricslam.geometry._jacobian import left_jacobian_sim


def from_rts(R: np.ndarray, t: np.ndarray, s: float) -> np.ndarray:
    """Build ``S`` (4, 4) from rotation (3, 3), translation (3,) and scale ``s > 0``."""
    if not (np.isfinite(s) and s > 0):
        raise GeometryError(f"Sim(3) scale must be finite and > 0, got {s}")
    S = np.eye(4)
    S[:3, :3] = s * np.asarray(R, dtype=float)
    S[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return S


def scale(S: np.ndarray) -> float:
    """The scale ``s`` of ``S`` (cube root of det of the 3x3 block)."""
    return float(np.cbrt(np.linalg.det(np.asarray(S, dtype=float)[:3, :3])))


def split(S: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``S`` -> ``(R, t, s)``."""
    S = np.asarray(S, dtype=float)
    if S.shape != (4, 4):
        raise GeometryError(f"expected a 4x4 similarity, got shape {S.shape}")
    s = scale(S)
    if not (np.isfinite(s) and s > 0):
        raise GeometryError(f"similarity has non-positive or non-finite scale {s}")
    return so3.check_rotation(S[:3, :3] / s, tol=1e-5), S[:3, 3].copy(), s


def inverse(S: np.ndarray) -> np.ndarray:
    """``S_b_a`` from ``S_a_b``."""
    R, t, s = split(S)
    return from_rts(R.T, -(R.T @ t) / s, 1.0 / s)


def exp(zeta: np.ndarray) -> np.ndarray:
    """``[ω, u, λ]`` (7,) -> ``S`` (4, 4)."""
    z = np.asarray(zeta, dtype=float).reshape(7)
    omega, u, lam = z[:3], z[3:6], float(z[6])
    return from_rts(so3.exp(omega), left_jacobian_sim(omega, lam) @ u, float(np.exp(lam)))


def log(S: np.ndarray) -> np.ndarray:
    """``S`` (4, 4) -> ``[ω, u, λ]`` (7,)."""
    R, t, s = split(S)
    omega = so3.log(R)
    lam = float(np.log(s))
    u = np.linalg.solve(left_jacobian_sim(omega, lam), t)
    return np.concatenate([omega, u, [lam]])


def retract(S: np.ndarray, zeta: np.ndarray) -> np.ndarray:
    """Right perturbation ``S @ Exp(ζ)``."""
    return S @ exp(zeta)


def local(S1: np.ndarray, S2: np.ndarray) -> np.ndarray:
    """``Log(S1⁻¹ S2)``."""
    return log(inverse(S1) @ S2)


def from_se3(T: np.ndarray, s: float = 1.0) -> np.ndarray:
    """Embed a rigid transform with scale ``s`` (rotation and translation kept)."""
    return from_rts(T[:3, :3], T[:3, 3], s)


def transform_points(S_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Apply ``S_a_b`` to points (N, 3) or (3,)."""
    p = np.asarray(p_b, dtype=float)
    return p @ S_a_b[:3, :3].T + S_a_b[:3, 3]
