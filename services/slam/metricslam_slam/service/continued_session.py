"""A camera's new SLAM session that continues its earlier trajectory as a new linked segment.

Used when a camera's session is replaced while the camera goes on: the service restarted (poses
from the state directory), the camera came back after an idle close, or the session reached
``max_session_keyframes`` (:mod:`metricslam_slam.service.cameras`). The earlier poses (``prior``)
are kept as they are; the new session starts at its own origin, and its poses are mapped into the
earlier world frame by the last earlier pose, so its first pose is where the camera was last
seen (not the origin):

    T_world_cam = T_world_origin · T_origin_cam      (T_world_origin: last prior pose)

Its segment ids follow the earlier ones (a new segment: consumers can tell the seam). The link
assumes the camera did not move while no session ran; the new segment has the monocular VO's
arbitrary scale until learned scale factors establish it again, like any new session.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from metricslam.datasets.base import Frame
from metricslam.errors import ServiceError
from metricslam.slam.types import PoseEstimate, SlamSession


def anchor_pose(prior: list[PoseEstimate]) -> PoseEstimate:
    """The pose a continuation starts from: the last earlier pose that is a real one."""
    return next((p for p in reversed(prior) if p.pose_valid), prior[-1])


class ContinuedSession:
    """A :class:`~metricslam.slam.types.SlamSession` continuing ``prior`` (module docstring).

    Args:
        inner: the new session (its own origin and segment ids).
        prior: the camera's earlier poses, in order (not empty).

    Attributes:
        T_world_origin: (4, 4) maps the inner session's world frame into the earlier one.
        first_segment_id: the inner session's segment 0 is published as this segment id.
    """

    def __init__(self, inner: SlamSession, prior: list[PoseEstimate]) -> None:
        if not prior:
            raise ServiceError("a continued session needs earlier poses")
        self.inner = inner
        self.prior = list(prior)
        self.anchor = anchor_pose(self.prior)
        self.T_world_origin = np.asarray(self.anchor.T_world_cam, dtype=np.float64).copy()
        self.first_segment_id = max(p.segment_id for p in self.prior) + 1

    def _mapped(self, est: PoseEstimate) -> PoseEstimate:
        return dataclasses.replace(est, T_world_cam=self.T_world_origin @ np.asarray(est.T_world_cam),
                                   segment_id=est.segment_id + self.first_segment_id)

    def process(self, frame: Frame) -> PoseEstimate:
        return self._mapped(self.inner.process(frame))

    def trajectory(self) -> list[PoseEstimate]:
        """The earlier poses, then the new session's current best poses (mapped)."""
        return self.prior + [self._mapped(e) for e in self.inner.trajectory()]

    def stats(self) -> dict:
        stats = dict(self.inner.stats())
        stats["continued"] = {"prior_poses": len(self.prior), "first_segment_id": self.first_segment_id,
                              "anchor_frame_index": self.anchor.frame_index}
        return stats

    def close(self) -> None:
        self.inner.close()

    def __getattr__(self, name: str):
        # the back end, VO, ... of the inner session (map topics, viewer); only reached for
        # names this class does not define
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)
