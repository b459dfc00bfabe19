"""Plain records the global back end keeps: per-keyframe bookkeeping, accepted loops and loop
decisions."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class KeyframeRecord:
    """What the back end keeps of each keyframe it has received."""

    kf_id: int
    frame_index: int
    segment_id: int
    epoch: int
    T_vo_kf: np.ndarray  # keyframe pose in the VO frame of its epoch (its own units)
    step_length: float = 1.0  # odometry step into this keyframe, in its predecessor's units


@dataclass(frozen=True)
class LoopRecord:
    """A loop accepted into the graph (ids and input frame indices of both keyframes)."""

    kf_old: int
    kf_new: int
    frame_old: int
    frame_new: int
    n_inliers: int


@dataclass(frozen=True)
class LoopDecision:
    """Outcome of :meth:`~.sim3_graph.GlobalPoseGraph.add_loop`."""

    accepted: bool
    kf_old: int
    kf_new: int
    mahalanobis_sq: float
    reason: str
