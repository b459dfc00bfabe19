"""Builds one :class:`metricslam.slam.types.SlamSession` per camera for the service.

``pipeline``: the real SLAM core, assembled by :func:`metricslam.slam.session_builder.build_session`
from the service's :class:`~metricslam.slam.system_config.SystemConfig` (with scale on, learned
scale factors from ``depth_source`` — the HTTP depth service — or, when that is None, the
in-process ONNX model). ``identity``: transport only — every frame gets the identity pose;
used to measure the service's Zenoh/queue overhead without the VO cost.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.datasets.base import Frame
from metricslam.errors import ServiceError
from metricslam.slam.session_builder import build_session
from metricslam.slam.system_config import SystemConfig
from metricslam.slam.types import PoseEstimate, SlamSession, TrackingState

SessionFactory = Callable[[str, PinholeCamera], SlamSession]


class IdentitySession:
    """A SlamSession that answers every frame with the identity pose (transport benchmarks)."""

    def __init__(self) -> None:
        self._poses: list[PoseEstimate] = []

    def process(self, frame: Frame) -> PoseEstimate:
        pose = PoseEstimate(frame_index=frame.index, t_ns=frame.t_ns, T_world_cam=np.eye(4),
                            state=TrackingState.TRACKING)
        self._poses.append(pose)
        return pose

    def trajectory(self) -> list[PoseEstimate]:
        return list(self._poses)

    def stats(self) -> dict:
        return {"frames": len(self._poses), "mode": "identity"}

    def close(self) -> None:
        pass


def make_session_factory(kind: str, config: SystemConfig | None = None,
                         depth_source: object | None = None) -> SessionFactory:
    """A ``(camera_id, camera) -> SlamSession`` factory.

    Args:
        kind: ``pipeline`` (:func:`metricslam.slam.session_builder.build_session`, the same
            builder offline runs use) or ``identity``.
        config: the sessions' system configuration (default: :class:`SystemConfig` defaults).
        depth_source: shared by every session (the HTTP depth client); None: each session runs
            the in-process model when ``config.depth.use_scale``.

    Raises:
        ServiceError: unknown ``kind``.
    """
    if kind == "identity":
        return lambda camera_id, camera: IdentitySession()
    if kind != "pipeline":
        raise ServiceError(f"unknown session kind {kind!r}; use 'pipeline' or 'identity'")
    config = config if config is not None else SystemConfig()

    def factory(camera_id: str, camera: PinholeCamera) -> SlamSession:
        return build_session(camera, config, depth_source=depth_source)

    return factory
