"""Reprojection residual of an inverse-depth landmark, its analytic Jacobians, and Huber weights.

A landmark hosted in keyframe ``h`` is its host pixel ``u`` (bearing ``f = K⁻¹ [u, 1]``) and its
inverse depth ``ρ`` (1/VO-units): ``p_h = f / ρ``. Observed in keyframe ``t`` it projects to
``π(K q)`` with ``q = R_t_h f + ρ t_t_h`` (``= ρ p_t``; scaling by ``ρ`` keeps far points, ρ → 0,
well conditioned). This is the paper's eq. (8).

Jacobians are with respect to **right** perturbations of ``T_world_h`` and ``T_world_t``
(tangent ``[ω, v]``, ``docs/conventions.md``) and to ``ρ``. Everything is vectorized over N
observations: shapes are (N, ...) throughout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Projection:
    """Residuals and Jacobians of N observations.

    Attributes:
        residual_px: (N, 2) predicted minus observed pixel.
        J_host: (N, 2, 6) d residual / d right-perturbation of ``T_world_host``.
        J_target: (N, 2, 6) d residual / d right-perturbation of ``T_world_target``.
        J_rho: (N, 2) d residual / d inverse depth.
        valid: (N,) the point is in front of the target camera.
    """

    residual_px: np.ndarray
    J_host: np.ndarray
    J_target: np.ndarray
    J_rho: np.ndarray
    valid: np.ndarray


def skew(v: np.ndarray) -> np.ndarray:
    """Batched hat operator: (N, 3) -> (N, 3, 3)."""
    out = np.zeros((v.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def relative_poses(T_world_host: np.ndarray, T_world_target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R_t_h (N,3,3), t_t_h (N,3))`` from batches of (N, 4, 4) world poses."""
    R_wh, t_wh = T_world_host[:, :3, :3], T_world_host[:, :3, 3]
    R_wt, t_wt = T_world_target[:, :3, :3], T_world_target[:, :3, 3]
    R_tw = np.transpose(R_wt, (0, 2, 1))
    R_th = R_tw @ R_wh
    t_th = np.einsum("nij,nj->ni", R_tw, t_wh - t_wt)
    return R_th, t_th


def project(T_world_host: np.ndarray, T_world_target: np.ndarray, bearing_h: np.ndarray,
            rho: np.ndarray, uv_obs_px: np.ndarray, K: np.ndarray,
            with_jacobians: bool = True, host_jacobian: bool = True) -> Projection:
    """Residuals (and Jacobians) of observations ``uv_obs_px`` (N, 2) of landmarks.

    Args:
        T_world_host, T_world_target: (N, 4, 4) poses of host and observing keyframes.
        bearing_h: (N, 3) host bearings ``K⁻¹ [u, v, 1]``.
        rho: (N,) inverse depths in the host frame.
        uv_obs_px: (N, 2) observed pixels in the target keyframe.
        K: (3, 3) intrinsics.
        with_jacobians: False skips all Jacobians (zeros); ``host_jacobian=False`` skips only
            ``J_host`` (zeros), for motion-only solves.
    """
    R_th, t_th = relative_poses(T_world_host, T_world_target)
    Rf = np.einsum("nij,nj->ni", R_th, bearing_h)
    q = Rf + rho[:, None] * t_th
    z = q[:, 2]
    valid = z > 1e-9 * np.maximum(1.0, np.abs(rho))
    zs = np.where(valid, z, 1.0)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    uv = np.stack([fx * q[:, 0] / zs + cx, fy * q[:, 1] / zs + cy], axis=1)
    r = uv - uv_obs_px
    n = len(rho)
    if not with_jacobians:
        e = np.zeros((n, 2, 6))
        return Projection(r, e, e, np.zeros((n, 2)), valid)
    J_pi = np.zeros((n, 2, 3))
    J_pi[:, 0, 0] = fx / zs
    J_pi[:, 0, 2] = -fx * q[:, 0] / zs**2
    J_pi[:, 1, 1] = fy / zs
    J_pi[:, 1, 2] = -fy * q[:, 1] / zs**2
    # dq/dξ_host = R_t_h [-[f]×, ρ I];  dq/dξ_target = [[q]×, -ρ I];  dq/dρ = t_t_h
    J_qt = np.concatenate([skew(q), -rho[:, None, None] * np.eye(3)[None]], axis=2)
    J_target = J_pi @ J_qt
    if host_jacobian:
        J_qh = np.concatenate([-R_th @ skew(bearing_h), rho[:, None, None] * R_th], axis=2)
        J_host = J_pi @ J_qh
    else:  # motion-only callers: the host (world) is fixed
        J_host = np.zeros((n, 2, 6))
    J_rho = np.einsum("nij,nj->ni", J_pi, t_th)
    return Projection(r, J_host, J_target, J_rho, valid)


def huber_weights(residual_px: np.ndarray, huber_px: float) -> np.ndarray:
    """IRLS weights (N,) of the Huber norm on the 2-D residual length."""
    norm = np.linalg.norm(residual_px, axis=1)
    return np.where(norm <= huber_px, 1.0, huber_px / np.maximum(norm, 1e-12))


def huber_cost(residual_px: np.ndarray, huber_px: float) -> np.ndarray:
    """Per-observation Huber cost (N,): ``r²`` inside, ``2k|r| − k²`` outside (no 1/2)."""
    norm = np.linalg.norm(residual_px, axis=1)
    return np.where(norm <= huber_px, norm**2, 2.0 * huber_px * norm - huber_px**2)


def triangulate_inverse_depth(T_world_host: np.ndarray, T_world_target: np.ndarray,
                              bearing_h: np.ndarray, xy_target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form 1-D least squares for ρ from one extra view.

    Args:
        T_world_host, T_world_target: (N, 4, 4) poses.
        bearing_h: (N, 3) host bearings; xy_target: (N, 2) normalized coordinates in the target.

    Returns:
        ``(rho (N,), parallax_rad (N,))``; ρ is NaN where the baseline gives no constraint.
    """
    R_th, t_th = relative_poses(T_world_host, T_world_target)
    Rf = np.einsum("nij,nj->ni", R_th, bearing_h)
    x, y = xy_target[:, 0], xy_target[:, 1]
    a = np.stack([t_th[:, 0] - x * t_th[:, 2], t_th[:, 1] - y * t_th[:, 2]], axis=1)
    b = np.stack([x * Rf[:, 2] - Rf[:, 0], y * Rf[:, 2] - Rf[:, 1]], axis=1)
    den = np.sum(a * a, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(den > 1e-18, np.sum(a * b, axis=1) / den, np.nan)
    ray_t = np.concatenate([xy_target, np.ones((len(x), 1))], axis=1)
    c = np.sum(Rf * ray_t, axis=1) / (np.linalg.norm(Rf, axis=1) * np.linalg.norm(ray_t, axis=1))
    return rho, np.arccos(np.clip(c, -1.0, 1.0))
