"""Motion-only bundle adjustment: one camera pose against known world points (Gauss-Newton,
Huber). Used to track every frame against the window map and to initialize new keyframes.

Reuses :func:`reprojection.project` with an identity "host", bearing = world point and ρ = 1,
so ``q = R_cam_world p_world + t_cam_world`` and ``J_target`` is the pose Jacobian.
"""

from __future__ import annotations

import cv2
import numpy as np

from metricslam.slam.vo import lie
from metricslam.slam.vo.reprojection import huber_weights, project


def estimate_pose(T_world_cam: np.ndarray, p_world: np.ndarray, uv_px: np.ndarray, K: np.ndarray,
                  huber_px: float, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Refine ``T_world_cam`` (4, 4) from points (N, 3) and their pixels (N, 2).

    Returns:
        ``(T_world_cam, inliers (N,) bool)``; inliers have a residual below ``3·huber_px`` and
        positive depth.
    """
    n = len(p_world)
    T = np.array(T_world_cam, dtype=float)
    if n < 3:
        return T, np.zeros(n, dtype=bool)
    eye = np.repeat(np.eye(4)[None], n, axis=0)
    rho = np.ones(n)
    for it in range(iterations):
        Tn = np.repeat(T[None], n, axis=0)
        pr = project(eye, Tn, p_world, rho, uv_px, K, host_jacobian=False)
        # wide robust kernel first (the prediction may be pixels off), then the nominal one
        k = huber_px * max(1.0, 8.0 / 2.0**it)
        w = huber_weights(pr.residual_px, k) * pr.valid
        if k == huber_px:  # once converged near the solution, ignore gross outliers entirely
            w = w * (np.linalg.norm(pr.residual_px, axis=1) < 3.0 * huber_px)
        J = pr.J_target.reshape(-1, 6)  # (2N, 6): one GEMM instead of a batched einsum
        WJ = J * np.repeat(w, 2)[:, None]
        H = WJ.T @ J
        g = WJ.T @ pr.residual_px.reshape(-1)
        try:
            dx = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        T = lie.retract(T[None], dx[None])[0]
        if np.linalg.norm(dx) < 1e-8:
            break
    pr = project(eye, np.repeat(T[None], n, axis=0), p_world, rho, uv_px, K, with_jacobians=False)
    inl = pr.valid & (np.linalg.norm(pr.residual_px, axis=1) < 3.0 * huber_px)
    return T, inl


def relocalize_pnp(p_world: np.ndarray, uv_px: np.ndarray, K: np.ndarray, huber_px: float,
                   iterations: int) -> tuple[np.ndarray, np.ndarray] | None:
    """PnP-RANSAC (OpenCV) + :func:`estimate_pose` refinement, for when the motion model's
    prediction was too far off (sudden motion). Returns ``(T_world_cam, inliers)`` or None."""
    if len(p_world) < 6:
        return None
    ok, rvec, tvec, _ = cv2.solvePnPRansac(p_world.astype(np.float64), uv_px.astype(np.float64),
                                           K, None, iterationsCount=200,
                                           reprojectionError=3.0 * huber_px,
                                           flags=cv2.SOLVEPNP_EPNP)
    if not ok:
        return None
    T_cam_world = np.eye(4)
    T_cam_world[:3, :3] = cv2.Rodrigues(rvec)[0]
    T_cam_world[:3, 3] = tvec.ravel()
    return estimate_pose(lie.inverse(T_cam_world[None])[0], p_world, uv_px, K, huber_px, iterations)
