"""A camera's continuous odometry stream (``metricslam/<camera_id>/odom``) beside its live poses.

A thin adapter over :class:`metricslam.trajectory.continuous.ContinuousOdometry`: it follows
the camera's sessions (each new one, continued sessions included, is attached so the back end's
warps reach it) and publishes one :class:`~metricslam.wire.odometry_message.OdometryMessage` per
published pose. The stream stays continuous across session roll-overs and restarts inside one
service run (a new session is a new segment: held for a frame, then blended in).
"""

from __future__ import annotations

import logging
from typing import Callable

from metricslam.slam.types import PoseEstimate, SlamSession
from metricslam.trajectory.continuous import ContinuousOdometry, ContinuousOdometryConfig
from metricslam.wire.codec import Message
from metricslam.wire.odometry_message import OdometryMessage

log = logging.getLogger(__name__)


class OdometryStream:
    """Args: ``camera_id``; ``publish(topic, message)`` (the camera worker's); ``config``."""

    def __init__(self, camera_id: str, publish: Callable[[str, Message], None],
                 config: ContinuousOdometryConfig | None = None) -> None:
        self.camera_id = camera_id
        self._publish = publish
        self.odometry = ContinuousOdometry(config)

    def attach(self, session: SlamSession) -> None:
        """Follow a new session's corrections (call before its first frame)."""
        self.odometry.attach(session)

    def after_pose(self, est: PoseEstimate, frame_id: str = "world") -> None:
        """Publish the continuous pose of the live pose ``est`` (in ``frame_id``) just published
        (never raises: the odometry stream must not disturb the poses)."""
        try:
            message = OdometryMessage.from_pose(self.camera_id, self.odometry.update(est))
            if frame_id != "world":
                message = message.model_copy(update={"frame_id": frame_id})
            self._publish("odom", message)
        except Exception:  # noqa: BLE001
            log.exception("camera %s: continuous odometry of frame %d failed", self.camera_id, est.frame_index)
