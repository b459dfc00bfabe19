"""Absolute trajectory error (ATE): RMSE of position differences after an optional alignment.

Three flavours, all over the positions of ``T_world_cam`` (N, 4, 4), metres:

* unaligned — the estimate as written (meaningful when both start at the identity, as KITTI);
* SE(3)-aligned — rigid Umeyama alignment of the estimate onto the ground truth (no scale, so a
  metric-scale error shows up here);
* Sim(3)-aligned — Umeyama with scale; its scale ``s`` (applied to the estimate) gives
  ``scale_ratio = 1 / s`` = estimate size / true size.

Same definitions as evo's APE on the translation part. When the ground truth is degenerate for
alignment (a straight line, or standing still) the aligned numbers are None and ``note`` says
why; the unaligned RMSE is always given. See ``docs/conventions.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from metricslam.errors import AlignmentError, EvaluationError
from metricslam.geometry import align, sim3


@dataclass(frozen=True)
class AteResult:
    """ATE numbers in metres, the Sim(3) alignment and its scale ratio.

    Attributes:
        rmse_unaligned_m: RMSE without alignment.
        rmse_se3_m: RMSE after rigid alignment.
        rmse_sim3_m: RMSE after similarity alignment.
        S_gt_est: the Sim(3) alignment (4, 4) mapping estimate into ground-truth world.
        scale_ratio: estimate size / true size (``1 / scale(S_gt_est)``); 1.0 is metric.
        err_se3_m: (N,) per-frame position error after rigid alignment (for plots).
    """

    rmse_unaligned_m: float
    rmse_se3_m: float | None
    rmse_sim3_m: float | None
    S_gt_est: np.ndarray | None
    scale_ratio: float | None
    err_se3_m: np.ndarray | None
    note: str | None = None

    @property
    def scale_error_pct(self) -> float | None:
        """``100·|scale_ratio − 1|`` (None without an alignment)."""
        return None if self.scale_ratio is None else 100.0 * abs(self.scale_ratio - 1.0)


def rmse(err: np.ndarray) -> float:
    """Root mean square of an error vector (N,)."""
    return float(np.sqrt(np.mean(np.square(err))))


def position_errors(T_world_cam_gt: np.ndarray, T_world_cam_est: np.ndarray) -> np.ndarray:
    """|p_est − p_gt| per frame, (N,) metres, no alignment."""
    return np.linalg.norm(T_world_cam_est[:, :3, 3] - T_world_cam_gt[:, :3, 3], axis=1)


def absolute_trajectory_error(T_world_cam_gt: np.ndarray, T_world_cam_est: np.ndarray) -> AteResult:
    """ATE unaligned / SE(3) / Sim(3) of frame-aligned trajectories (N, 4, 4).

    Raises:
        EvaluationError: the shapes differ.
    """
    gt = np.asarray(T_world_cam_gt, dtype=float)
    est = np.asarray(T_world_cam_est, dtype=float)
    if gt.shape != est.shape:
        raise EvaluationError(f"trajectories differ in shape: gt {gt.shape}, estimate {est.shape}")
    unaligned = rmse(position_errors(gt, est))
    try:
        _, est_se3 = align.align_trajectory(est, gt, with_scale=False)
        S_gt_est, est_sim3 = align.align_trajectory(est, gt, with_scale=True)
    except AlignmentError as exc:
        note = f"aligned ATE and scale ratio are undefined (null): {exc}"
        return AteResult(unaligned, None, None, None, None, None, note)
    err_se3 = position_errors(gt, est_se3)
    return AteResult(
        rmse_unaligned_m=unaligned,
        rmse_se3_m=rmse(err_se3),
        rmse_sim3_m=rmse(position_errors(gt, est_sim3)),
        S_gt_est=S_gt_est,
        scale_ratio=1.0 / sim3.scale(S_gt_est),
        err_se3_m=err_se3,
    )
