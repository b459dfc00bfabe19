"""The continuous odometry stream on the wire (``metricslam/<id>/odom``), beside the live poses.

One :class:`OdometryMessage` per processed frame, from
:class:`metricslam.trajectory.continuous.ContinuousOdometry`: a pose that never jumps (the live
pose's corrections blended in over ``horizon_s``), its split into ``T_world_odom · T_odom_cam``
(REP 105's map → odom), the camera's twist, and what the pose's scale rests on. Encoded by
:mod:`metricslam.wire.codec` like every message (its ``MESSAGE_TYPES`` lists it).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from pydantic import Field, field_validator

from metricslam.slam.types import ScaleState, TrackingState
from metricslam.wire.base import FrameId, Message, as_array, finite_pose


class OdometryMessage(Message):
    """The continuous pose of one frame (``metricslam/<id>/odom``).

    ``T_world_cam``: (4, 4) float64 continuous camera-to-world (world units: metres once
    ``scale_state`` is ``metric``); equal to the ``…/pose`` message's ``T_world_cam`` of the same
    frame once ``correction_m`` and ``correction_rad`` are 0. ``T_world_odom`` (4, 4): the blended
    correction; ``T_odom_cam`` (4, 4): the odometry pose (moves only by frame-to-frame motion).
    ``twist_cam``: (6,) float64 ``[ω rad/s, v world units/s]`` in the camera frame (zeros for a
    frame without a tracked pose). ``correction_m`` / ``correction_rad``: distance and angle still
    to blend in (this pose vs the live one); ``blend_until_t_ns``: when it will be in.
    ``scale_state`` / ``scale_factors``: those of the live pose (:class:`ScaleState`).
    ``frame_id``: the frame of the poses (``"map"``: ``T_world_*`` are ``T_map_*``; the stream
    starts over when a session relocalizes into the map).
    """

    KIND: ClassVar[str] = "odometry"
    ARRAYS: ClassVar[tuple[str, ...]] = ("T_world_cam", "T_world_odom", "T_odom_cam", "twist_cam")

    frame_index: int = Field(ge=0)
    t_ns: int = Field(ge=0)
    state: TrackingState
    segment_id: int = Field(default=0, ge=0)
    scale_state: ScaleState
    scale_factors: int = Field(default=0, ge=0)
    correction_m: float = Field(ge=0)
    correction_rad: float = Field(ge=0)
    blend_until_t_ns: int
    frame_id: FrameId = "world"
    T_world_cam: np.ndarray
    T_world_odom: np.ndarray
    T_odom_cam: np.ndarray
    twist_cam: np.ndarray

    @field_validator("T_world_cam", "T_world_odom", "T_odom_cam")
    @classmethod
    def _pose(cls, T: Any, info) -> np.ndarray:
        return finite_pose(T, info.field_name)

    @field_validator("twist_cam")
    @classmethod
    def _twist(cls, twist: Any) -> np.ndarray:
        twist = as_array(twist, "float64", "twist_cam", (6,))
        if not np.all(np.isfinite(twist)):
            raise ValueError("twist_cam must be finite")
        return twist

    @classmethod
    def from_pose(cls, camera_id: str, pose: Any) -> "OdometryMessage":
        """From a :class:`metricslam.trajectory.continuous.ContinuousPose`."""
        return cls(camera_id=camera_id, frame_index=pose.frame_index, t_ns=pose.t_ns, state=pose.state,
                   segment_id=pose.segment_id, scale_state=pose.scale_state, scale_factors=pose.scale_factors,
                   correction_m=pose.correction_m, correction_rad=pose.correction_rad,
                   blend_until_t_ns=pose.blend_until_t_ns, T_world_cam=pose.T_world_cam,
                   T_world_odom=pose.T_world_odom, T_odom_cam=pose.T_odom_cam, twist_cam=pose.twist_cam)
