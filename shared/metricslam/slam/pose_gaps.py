"""Poses for the frames that have none of their own (:meth:`~metricslam.slam.pipeline.SlamPipeline.trajectory`):
interpolated between the nearest posed frames in one world frame, or placeholders marked invalid."""

from __future__ import annotations

import dataclasses

import numpy as np

from metricslam.geometry import so3
from metricslam.slam.types import PoseEstimate


def fill_pose_gaps(poses: list[PoseEstimate], own: list[bool], in_graph: list[bool],
                   relinked: frozenset[int] | set[int] = frozenset()) -> list[PoseEstimate]:
    """Give every frame without a pose of its own (``own[k]`` False) an interpolated pose, or
    a placeholder marked ``pose_valid=False`` (see :meth:`SlamPipeline.trajectory`). Frames with
    a pose of their own are returned as they are. No pose is interpolated across the start of a
    ``relinked`` segment: a relocalization replaced its link to the previous one, so how the
    camera got there is unknown (:mod:`metricslam.slam.map.segments`)."""
    n = len(poses)
    if all(own):
        return poses
    left: list[int | None] = [None] * n  # nearest frame at or before k with a pose of its own
    right: list[int | None] = [None] * n  # ... at or after k
    for k in range(n):
        left[k] = k if own[k] else (left[k - 1] if k else None)
    for k in reversed(range(n)):
        right[k] = k if own[k] else (right[k + 1] if k + 1 < n else None)
    out = list(poses)
    for k, est in enumerate(poses):
        if own[k]:
            continue
        a, b = left[k], right[k]
        interpolated, valid = False, True
        if a is not None and b is not None and (
                poses[a].segment_id == poses[b].segment_id or (in_graph[a] and in_graph[b] and not any(
                    s in relinked for s in range(poses[a].segment_id + 1, poses[b].segment_id + 1)))):
            T, interpolated = interpolate_pose(poses[a], poses[b], est.t_ns, k - a, b - a), True
        elif a is None:  # before the first pose the VO has no map: it sits at its world origin
            T, valid = est.T_world_cam, False
        else:  # the side in this frame's own segment, else the earlier one
            later_is_own = (b is not None and poses[b].segment_id == est.segment_id
                            and poses[a].segment_id != est.segment_id)
            T, valid = poses[b if later_is_own else a].T_world_cam.copy(), False
        out[k] = dataclasses.replace(est, T_world_cam=T, interpolated=interpolated, pose_valid=valid)
    return out


def interpolate_pose(a: PoseEstimate, b: PoseEstimate, t_ns: int, steps_from_a: int,
                      steps_a_to_b: int) -> np.ndarray:
    """``T_world_cam`` at ``t_ns`` between ``a`` and ``b``: position linear, rotation along the
    geodesic (``R_a·Exp(α·Log(R_aᵀ·R_b))``), α from the timestamps (from frame counts if the
    timestamps do not increase)."""
    span_ns = b.t_ns - a.t_ns
    alpha = (t_ns - a.t_ns) / span_ns if span_ns > 0 else steps_from_a / steps_a_to_b
    alpha = min(max(float(alpha), 0.0), 1.0)
    R_a, R_b = so3.project_to_so3(a.T_world_cam[:3, :3]), so3.project_to_so3(b.T_world_cam[:3, :3])
    T = np.eye(4)
    T[:3, :3] = R_a @ so3.exp(alpha * so3.log(R_a.T @ R_b))
    T[:3, 3] = (1.0 - alpha) * a.T_world_cam[:3, 3] + alpha * b.T_world_cam[:3, 3]
    return T
