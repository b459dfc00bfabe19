"""``metricslam/<cam>/odom`` through the real SLAM service (in-process, real zenoh on loopback):
a session whose back end warps its world at one frame (the live ``…/pose`` jumps by metres)
gives a continuous ``…/odom`` beside it that converges to the live pose."""

from __future__ import annotations

import time

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.geometry import se3, sim3, so3
from metricslam.slam.events import EventBus, WarpApplied
from metricslam.slam.system_config import SystemConfig
from metricslam.slam.types import PoseEstimate, ScaleState, TrackingState
from metricslam.trajectory.continuous import apply_sim3_rigid
from metricslam.wire import keys
from metricslam.wire.codec import decode_as
from metricslam.wire.odometry_message import OdometryMessage
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.slam_service import SlamService
from metricslam_slam.supervisor.launcher import free_port
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import FramePublisher, PoseRecorder
from metricslam_slam.zenoh_config import open_client

CAMERA = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=31.5, cy_px=23.5, width_px=64, height_px=48)
N_FRAMES, WARP_AT = 60, 10
S_WARP = sim3.from_rts(so3.exp([0.0, 0.02, 0.0]), [0.5, 0.0, -1.0], 1.2)


def true_pose(k: int) -> np.ndarray:
    """Driving forward 1 m a frame (10 Hz), 30 m from the world origin."""
    return se3.from_rt(np.eye(3), [30.0, 0.0, 1.0 * k])


class WarpingSession:
    """A SlamSession whose back end warps the world by ``S_WARP`` at frame ``WARP_AT``."""

    def __init__(self, camera_id: str, camera: PinholeCamera) -> None:
        self.backend = type("Backend", (), {})()
        self.backend.events = EventBus()
        self._estimates: list[PoseEstimate] = []

    def process(self, frame) -> PoseEstimate:
        k = frame.index
        if k == WARP_AT:
            self.backend.events.emit(WarpApplied(S_WARP, sim3.scale(S_WARP), 1))
        T = true_pose(k) if k < WARP_AT else apply_sim3_rigid(S_WARP, true_pose(k))
        est = PoseEstimate(k, frame.t_ns, T, TrackingState.TRACKING, scale_state=ScaleState.METRIC)
        self._estimates.append(est)
        return est

    def trajectory(self) -> list[PoseEstimate]:
        return list(self._estimates)

    def stats(self) -> dict:
        return {}

    def close(self) -> None:
        pass


def test_odom_topic_is_continuous_beside_the_jumping_pose_topic() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    settings = SlamServiceSettings(zenoh_endpoint=endpoint, depth_url=None, status_period_s=0.2)
    service = SlamService(settings, session_factory=WarpingSession,  # a queue that drops nothing
                          config=SystemConfig(depth={"use_scale": False}, queues={"frames": 128})).start()
    client = open_client(endpoint)
    odom: list[OdometryMessage] = []
    sub = client.declare_subscriber(keys.key("cam0", "odom"),
                                    lambda s: odom.append(decode_as(s.payload.to_bytes(), OdometryMessage)))
    try:
        recorder = PoseRecorder(client, "cam0")
        time.sleep(0.3)
        pub = FramePublisher(client, "cam0")
        assert pub.wait_for_subscriber(10)
        image = np.zeros((48, 64), np.uint8)
        for k in range(N_FRAMES):
            pub.publish(k, k * 100_000_000, image, CAMERA)
        assert recorder.wait_frames(N_FRAMES, 20)
        deadline = time.monotonic() + 10
        while len(odom) < N_FRAMES and time.monotonic() < deadline:
            time.sleep(0.02)
        recorder.close()
    finally:
        sub.undeclare()
        client.close()
        service.stop()
        router.close()
    assert [m.frame_index for m in odom] == list(range(N_FRAMES))
    live = np.array([recorder.poses[k].T_world_cam for k in range(N_FRAMES)])
    cont = np.array([m.T_world_cam for m in odom])
    live_steps = np.linalg.norm(np.diff(live[:, :3, 3], axis=0), axis=1)
    cont_steps = np.linalg.norm(np.diff(cont[:, :3, 3], axis=0), axis=1)
    assert live_steps.max() > 5.0  # the warp moves the live pose by metres
    assert cont_steps.max() <= 2.0 * 1.2  # true motion is 1 m a frame, 1.2 in the warped units
    np.testing.assert_allclose(cont[:WARP_AT], live[:WARP_AT])  # nothing to blend before
    np.testing.assert_allclose(cont[-1], live[-1], atol=1e-9)  # in after the 2 s horizon
    assert odom[-1].correction_m < 1e-9 and odom[WARP_AT].correction_m > 5.0
    assert all(m.scale_state is ScaleState.METRIC for m in odom)
    assert abs(odom[30].twist_cam[5] - 12.0) < 1e-6  # forward, 1.2 units a frame at 10 Hz
