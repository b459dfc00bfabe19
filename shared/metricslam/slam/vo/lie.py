"""Batched closed-form SE(3) Exp/Log for the VO's inner loops.

Same conventions as :mod:`metricslam.geometry.se3` (tangent ``[ω, v]``, right perturbation,
``docs/conventions.md``) but vectorized over (N, ...) and without per-call validation: the
general-purpose helpers cost ~0.5 ms per call, which dominated window BA. Equality with
:mod:`metricslam.geometry.se3` is tested.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from metricslam.slam.vo.reprojection import skew

_SMALL = 1e-4


def _coefficients(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``A = sinθ/θ``, ``B = (1−cosθ)/θ²``, ``C = (θ−sinθ)/θ³`` with series near 0."""
    t2 = theta * theta
    small = theta < _SMALL
    ts = np.where(small, 1.0, theta)
    A = np.where(small, 1.0 - t2 / 6.0, np.sin(ts) / ts)
    B = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    C = np.where(small, 1.0 / 6.0 - t2 / 120.0, (ts - np.sin(ts)) / ts**3)
    return A, B, C


def exp(xi: np.ndarray) -> np.ndarray:
    """(N, 6) ``[ω, v]`` -> (N, 4, 4)."""
    xi = np.atleast_2d(xi)
    w, v = xi[:, :3], xi[:, 3:]
    theta = np.linalg.norm(w, axis=1)
    A, B, C = _coefficients(theta)
    W = skew(w)
    W2 = W @ W
    eye = np.eye(3)[None]
    R = eye + A[:, None, None] * W + B[:, None, None] * W2
    V = eye + B[:, None, None] * W + C[:, None, None] * W2
    T = np.zeros((len(xi), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = np.einsum("nij,nj->ni", V, v)
    T[:, 3, 3] = 1.0
    return T


def _so3_log(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) -> (N, 3) rotation vectors; closed form, scipy near θ = π."""
    c = np.clip(0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0), -1.0, 1.0)
    theta = np.arccos(c)
    vee = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    small = theta < _SMALL
    near_pi = theta > np.pi - 1e-3
    ok = ~small & ~near_pi
    k = np.where(small, 0.5 + theta**2 / 12.0, 0.0)
    k[ok] = theta[ok] / (2.0 * np.sin(theta[ok]))
    w = k[:, None] * vee
    if np.any(near_pi):
        w[near_pi] = Rotation.from_matrix(R[near_pi]).as_rotvec()
    return w


def log(T: np.ndarray) -> np.ndarray:
    """(N, 4, 4) -> (N, 6) ``[ω, v]``."""
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    R, t = T[:, :3, :3], T[:, :3, 3]
    w = _so3_log(R)
    theta = np.linalg.norm(w, axis=1)
    A, B, _ = _coefficients(theta)
    small = theta < _SMALL
    ts = np.where(small, 1.0, theta)
    # V⁻¹ = I − ½W + (1/θ²)(1 − A/(2B)) W²
    D = np.where(small, 1.0 / 12.0 + theta**2 / 720.0, (1.0 - A / (2.0 * B)) / ts**2)
    W = skew(w)
    Vinv = np.eye(3)[None] - 0.5 * W + D[:, None, None] * (W @ W)
    return np.concatenate([w, np.einsum("nij,nj->ni", Vinv, t)], axis=1)


def inverse(T: np.ndarray) -> np.ndarray:
    """(N, 4, 4) rigid inverses."""
    Rt = np.transpose(T[:, :3, :3], (0, 2, 1))
    out = np.zeros_like(T)
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def local(T1: np.ndarray, T2: np.ndarray) -> np.ndarray:
    """(N, 6) ``Log(T1⁻¹ T2)``."""
    return log(inverse(T1) @ T2)


def retract(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """(N, 4, 4) ``T @ Exp(ξ)`` with rotations re-orthonormalized (round-off control)."""
    out = T @ exp(xi)
    U, _, Vt = np.linalg.svd(out[:, :3, :3])
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= d[:, None]
    out[:, :3, :3] = U @ Vt
    return out
