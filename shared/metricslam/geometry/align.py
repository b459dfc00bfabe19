"""Umeyama least-squares alignment of point sets and trajectories (SE(3) and Sim(3)).

Finds ``S_gt_est`` minimizing ``Σ |p_gt - (s·R·p_est + t)|²`` (Umeyama 1991). With
``with_scale=False`` the scale is fixed to 1 (rigid SE(3) alignment). See ``docs/conventions.md``.
"""

from __future__ import annotations

import numpy as np

from metricslam.errors import AlignmentError
from metricslam.geometry import sim3


def umeyama(p_est: np.ndarray, p_gt: np.ndarray, with_scale: bool = True) -> np.ndarray:
    """Least-squares ``S_gt_est`` (4, 4) mapping points ``p_est`` (N, 3) onto ``p_gt`` (N, 3).

    Raises:
        AlignmentError: fewer than 3 points, non-finite values, or a degenerate (collinear or
            single-point) configuration for which rotation is not determined.
    """
    x = np.asarray(p_est, dtype=float)
    y = np.asarray(p_gt, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape != y.shape:
        raise AlignmentError(f"need two (N, 3) point sets of equal size, got {x.shape} and {y.shape}")
    n = x.shape[0]
    if n < 3:
        raise AlignmentError(f"alignment needs at least 3 points, got {n}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise AlignmentError("alignment input contains NaN or inf")
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    var_x = float(np.mean(np.sum(xc**2, axis=1)))
    cov = yc.T @ xc / n
    U, d, Vt = np.linalg.svd(cov)
    # Rotation is determined when the cross-covariance has rank >= 2 (non-collinear points).
    scale_ref = max(d[0], 1e-300)
    if var_x < 1e-12 or d[1] / scale_ref < 1e-9:
        raise AlignmentError(
            "degenerate alignment: points are (nearly) coincident or collinear; "
            "a trajectory needs motion in at least two directions to be aligned"
        )
    Sgn = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        Sgn[2, 2] = -1.0
    R = U @ Sgn @ Vt
    s = float(np.trace(np.diag(d) @ Sgn) / var_x) if with_scale else 1.0
    t = my - s * R @ mx
    return sim3.from_rts(R, t, s)


def align_trajectory(
    T_world_cam_est: np.ndarray, T_world_cam_gt: np.ndarray, with_scale: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Align estimated poses (N, 4, 4) to ground truth by their positions.

    Returns:
        ``(S_gt_est, T_aligned)`` where ``T_aligned[i]`` has rotation ``R·R_i`` and position
        ``s·R·t_i + t`` (rotations are not scaled), shape (N, 4, 4).
    """
    est = np.asarray(T_world_cam_est, dtype=float)
    gt = np.asarray(T_world_cam_gt, dtype=float)
    S = umeyama(est[:, :3, 3], gt[:, :3, 3], with_scale=with_scale)
    return S, apply_to_poses(S, est)


def apply_to_poses(S_a_b: np.ndarray, T_b_cam: np.ndarray) -> np.ndarray:
    """Left-apply a similarity to rigid poses (N, 4, 4): rotation ``R·R_i``, position ``S·t_i``."""
    R, t, s = sim3.split(S_a_b)
    out = np.array(T_b_cam, dtype=float, copy=True)
    out[:, :3, :3] = R @ out[:, :3, :3]
    out[:, :3, 3] = s * out[:, :3, 3] @ R.T + t
    return out
