"""Trajectory evaluation in pure numpy: KITTI devkit t_rel/r_rel, ATE (unaligned, SE(3),
Sim(3)), RPE, scale ratio, pooling over sequences. Plots live in :mod:`.plots` (matplotlib,
imported lazily). Definitions: ``docs/evaluation.md``; frames: ``docs/conventions.md``.
"""

from metricslam.evaluation.evaluator import (
    SequenceEvaluation,
    evaluate_files,
    evaluate_poses,
    evaluate_timed,
)
from metricslam.evaluation.kitti_metric import kitti_segment_errors, segment_errors
from metricslam.evaluation.pooling import build_report
from metricslam.evaluation.result import EvalReport, EvalResult

__all__ = [
    "EvalReport",
    "EvalResult",
    "SequenceEvaluation",
    "build_report",
    "evaluate_files",
    "evaluate_poses",
    "evaluate_timed",
    "kitti_segment_errors",
    "segment_errors",
]
