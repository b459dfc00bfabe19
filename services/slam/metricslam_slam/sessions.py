"""Builds one :class:`metricslam.slam.types.SlamSession` per camera for the service.

``pipeline``: the real SLAM core (``SlamPipeline`` + the global back end with loop closure; with
scale on, learned scale factors from ``depth_source`` — the HTTP depth service — or, when that is
None, the in-process ONNX model). ``identity``: transport only — every frame gets the identity pose;
used to measure the service's Zenoh/queue overhead without the VO cost.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.datasets.base import Frame
from metricslam.errors import ServiceError
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


def make_session_factory(kind: str, preset: str = "kitti", use_scale: bool = True,
                         depth_source: object | None = None) -> SessionFactory:
    """A ``(camera_id, camera) -> SlamSession`` factory.

    Raises:
        ServiceError: the SLAM core is not importable (``kind="pipeline"``).
    """
    if kind == "identity":
        return lambda camera_id, camera: IdentitySession()
    if kind != "pipeline":
        raise ServiceError(f"unknown session kind {kind!r}; use 'pipeline' or 'identity'")
    try:
        from metricslam.slam.backend_factory import make_backend
        from metricslam.slam.pipeline import SlamPipeline
        from metricslam.slam.vo.config import VOConfig
    except ImportError as exc:
        raise ServiceError(f"the SLAM core is not available ({exc}); "
                           "use session_kind=identity for transport-only runs") from None
    vo_config = VOConfig.preset(preset)

    def factory(camera_id: str, camera: PinholeCamera) -> SlamSession:
        backend = make_backend(camera, use_scale=use_scale, depth_source=depth_source)
        return SlamPipeline(camera, vo_config, backend=backend)

    return factory
