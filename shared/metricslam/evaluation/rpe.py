"""Relative pose error (RPE) between frames ``i`` and ``i + Δ`` (evo's ``evo_rpe`` definition).

``E_i = (Q_i⁻¹ Q_{i+Δ})⁻¹ (P_i⁻¹ P_{i+Δ})`` with ``Q`` the ground truth and ``P`` the estimate
(both ``T_world_cam``, (N, 4, 4)); the translation error is ``|trans(E_i)|`` in metres and the
rotation error ``angle(E_i)`` in degrees. No alignment is needed (relative motions). The RMSE
over all ``i`` is reported. See ``docs/conventions.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from metricslam.errors import EvaluationError


@dataclass(frozen=True)
class RpeResult:
    """RPE RMSE over all pairs ``(i, i + delta_frames)``.

    Attributes:
        delta_frames: the frame offset Δ.
        trans_rmse_m: RMSE of ``|trans(E_i)|`` in metres.
        rot_rmse_deg: RMSE of ``angle(E_i)`` in degrees.
        n_pairs: number of pairs.
    """

    delta_frames: int
    trans_rmse_m: float
    rot_rmse_deg: float
    n_pairs: int


def relative_errors(
    T_world_cam_gt: np.ndarray, T_world_cam_est: np.ndarray, delta_frames: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pair ``(|trans(E_i)| (M,) metres, angle(E_i) (M,) radians)``."""
    gt = np.asarray(T_world_cam_gt, dtype=float)
    est = np.asarray(T_world_cam_est, dtype=float)
    if gt.shape != est.shape:
        raise EvaluationError(f"trajectories differ in shape: gt {gt.shape}, estimate {est.shape}")
    if delta_frames < 1 or delta_frames >= gt.shape[0]:
        raise EvaluationError(
            f"RPE needs 1 <= delta_frames < number of frames ({gt.shape[0]}), got {delta_frames}"
        )
    d_gt = np.linalg.inv(gt[:-delta_frames]) @ gt[delta_frames:]
    d_est = np.linalg.inv(est[:-delta_frames]) @ est[delta_frames:]
    E = np.linalg.inv(d_gt) @ d_est
    t_err = np.linalg.norm(E[:, :3, 3], axis=1)
    c = 0.5 * (np.trace(E[:, :3, :3], axis1=1, axis2=2) - 1.0)
    r_err = np.arccos(np.clip(c, -1.0, 1.0))
    return t_err, r_err


def relative_pose_error(
    T_world_cam_gt: np.ndarray, T_world_cam_est: np.ndarray, delta_frames: int = 1
) -> RpeResult:
    """RPE RMSE for frame offset ``delta_frames``."""
    t_err, r_err = relative_errors(T_world_cam_gt, T_world_cam_est, delta_frames)
    return RpeResult(
        delta_frames=delta_frames,
        trans_rmse_m=float(np.sqrt(np.mean(t_err**2))),
        rot_rmse_deg=float(np.degrees(np.sqrt(np.mean(r_err**2)))),
        n_pairs=int(t_err.shape[0]),
    )
