"""Evaluate one estimated trajectory against ground truth: KITTI devkit segments, ATE, RPE.

Trajectories are ``T_world_cam`` (N, 4, 4). KITTI-format pairs must have one pose per frame;
time-stamped (TUM) estimates are first associated by timestamp with time-stamped ground truth
(TUM, EuRoC, or KITTI with its ``times.txt``: :mod:`.ground_truth`). See ``docs/evaluation.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from metricslam.errors import EvaluationError, TrajectoryError
from metricslam.evaluation.associate import DEFAULT_MAX_DIFF_NS, associate
from metricslam.evaluation.ate import AteResult, absolute_trajectory_error
from metricslam.evaluation.ground_truth import read_ground_truth
from metricslam.evaluation.kitti_metric import (
    SHORT_LENGTHS_M,
    SegmentErrors,
    kitti_segment_errors,
    trajectory_distances,
)
from metricslam.evaluation.result import EvalResult
from metricslam.evaluation.rpe import RpeResult, relative_pose_error
from metricslam.trajectory.io import read_trajectory


@dataclass(frozen=True)
class SequenceEvaluation:
    """Everything computed for one sequence (the result plus arrays for pooling and plots)."""

    result: EvalResult
    segments: SegmentErrors
    ate: AteResult
    rpe: RpeResult
    T_world_cam_gt: np.ndarray
    T_world_cam_est: np.ndarray


def _none_if_nan(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)


def evaluate_poses(
    T_world_cam_gt: np.ndarray,
    T_world_cam_est: np.ndarray,
    name: str = "sequence",
    rpe_delta_frames: int = 1,
    notes: list[str] | None = None,
) -> SequenceEvaluation:
    """All metrics for frame-aligned poses (N, 4, 4) (estimate frame ``i`` ↔ ground truth ``i``)."""
    gt = np.asarray(T_world_cam_gt, dtype=float)
    est = np.asarray(T_world_cam_est, dtype=float)
    if gt.ndim != 3 or gt.shape[1:] != (4, 4) or est.shape != gt.shape:
        raise EvaluationError(
            f"ground truth has {gt.shape[0] if gt.ndim == 3 else '?'} poses and the estimate "
            f"{est.shape[0] if est.ndim == 3 else '?'}: a KITTI-format estimate needs exactly one "
            "pose per ground-truth frame (or use TUM files with timestamps)"
        )
    if gt.shape[0] < 3:
        raise EvaluationError(f"need at least 3 poses to evaluate, got {gt.shape[0]}")
    if not (np.all(np.isfinite(gt)) and np.all(np.isfinite(est))):
        raise EvaluationError("a trajectory contains NaN or inf poses")
    notes = list(notes or [])
    seg = kitti_segment_errors(gt, est)
    short = seg.lengths_m == SHORT_LENGTHS_M
    if short:
        notes.append("no 100 m segment fits: t_rel/r_rel use lengths 10..50 m (not comparable "
                     "to KITTI leaderboard numbers)")
    if len(seg) == 0:
        notes.append("no 10 m segment fits either: t_rel/r_rel are undefined (null)")
    ate = absolute_trajectory_error(gt, est)
    if ate.note:
        notes.append(ate.note)
    rpe = relative_pose_error(gt, est, rpe_delta_frames)
    by_len = {f"{L:g}": [t, r, float(n)] for L, (t, r, n) in seg.by_length().items()}
    result = EvalResult(
        name=name,
        t_rel_pct=_none_if_nan(seg.t_rel_pct),
        r_rel_deg_per_100m=_none_if_nan(seg.r_rel_deg_per_100m),
        ate_rmse_m=ate.rmse_se3_m,
        ate_rmse_sim3_m=ate.rmse_sim3_m,
        scale_ratio=ate.scale_ratio,
        scale_error_pct=ate.scale_error_pct,
        n_frames=int(gt.shape[0]),
        path_length_m=float(trajectory_distances(gt)[-1]),
        t_rel_lengths_m=seg.used_lengths_m,
        ate_rmse_unaligned_m=ate.rmse_unaligned_m,
        rpe_trans_rmse_m=rpe.trans_rmse_m,
        rpe_rot_rmse_deg=rpe.rot_rmse_deg,
        rpe_delta_frames=rpe.delta_frames,
        n_segments=len(seg),
        t_rel_by_length=by_len,
        short_sequence=short,
        notes=notes,
    )
    return SequenceEvaluation(result, seg, ate, rpe, gt, est)


def evaluate_timed(
    t_ns_gt: np.ndarray,
    T_world_cam_gt: np.ndarray,
    t_ns_est: np.ndarray,
    T_world_cam_est: np.ndarray,
    name: str = "sequence",
    max_diff_ns: int = DEFAULT_MAX_DIFF_NS,
    rpe_delta_frames: int = 1,
    notes: list[str] | None = None,
) -> SequenceEvaluation:
    """Associate by nearest timestamp, then :func:`evaluate_poses` on the matched pairs.

    Devkit segments then start every 10 *associated* frames (the devkit assumes 10 Hz).
    """
    i_gt, i_est = associate(t_ns_gt, t_ns_est, max_diff_ns)
    notes = list(notes or [])
    n_est = len(t_ns_est)
    if len(i_est) < n_est:
        notes.append(f"{n_est - len(i_est)} of {n_est} estimated poses had no ground truth within "
                     f"{max_diff_ns / 1e6:g} ms and were left out")
    return evaluate_poses(np.asarray(T_world_cam_gt)[i_gt], np.asarray(T_world_cam_est)[i_est],
                          name, rpe_delta_frames, notes)


def evaluate_files(
    gt_path: str | Path,
    est_path: str | Path,
    fmt: str = "auto",
    name: str | None = None,
    max_diff_ns: int = DEFAULT_MAX_DIFF_NS,
    rpe_delta_frames: int = 1,
    gt_times: str | Path | None = None,
) -> SequenceEvaluation:
    """Evaluate an estimate file against ground truth.

    The estimate is a KITTI or TUM file (:func:`read_trajectory`, ``fmt``); the ground truth a
    KITTI, TUM or EuRoC file or a dataset folder (:func:`~metricslam.evaluation.ground_truth.read_ground_truth`;
    ``gt_times``: a KITTI ``times.txt`` for a KITTI pose file). A KITTI estimate pairs with
    per-frame (KITTI) ground truth line by line; a TUM estimate with time-stamped ground truth by
    nearest timestamp.

    Raises:
        TrajectoryError: a file is malformed, or the two cannot be paired (what to pass instead
            is in the message).
        EvaluationError: the pair cannot be evaluated (pose counts differ, too short, ...).
    """
    name = name or Path(est_path).stem
    t_est, T_est = read_trajectory(est_path, "auto" if fmt == "euroc" else fmt)
    gt = read_ground_truth(gt_path, fmt, times=gt_times)
    if t_est is None:
        if not gt.per_frame:
            raise TrajectoryError(
                f"the estimate is a KITTI file (no timestamps) but the ground truth {gt_path} is "
                "time-stamped; give both in the same format: write the estimate with "
                "`metricslam run --format tum`", est_path,
            )
        if gt.T_world_cam.shape[0] != T_est.shape[0]:
            raise TrajectoryError(
                f"the estimate has {T_est.shape[0]} poses but the ground truth {gt_path} has "
                f"{gt.T_world_cam.shape[0]}; KITTI-format files must have one line per frame", est_path,
            )
        return evaluate_poses(gt.T_world_cam, T_est, name, rpe_delta_frames, gt.notes)
    if gt.t_ns is None:
        raise TrajectoryError(
            f"the estimate is time-stamped (TUM) but the ground truth {gt_path} is a KITTI file "
            "without timestamps; give both in the same format, or add the sequence's times.txt "
            "(--gt-times), or pass the sequence folder as --gt", est_path,
        )
    return evaluate_timed(gt.t_ns, gt.T_world_cam, t_est, T_est, name, max_diff_ns, rpe_delta_frames,
                          gt.notes)
