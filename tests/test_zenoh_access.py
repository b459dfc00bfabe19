"""Zenoh access control with a real router on loopback: loopback-only listening, user/password
authentication (wrong or missing credentials cannot connect) and the ACL that lets only the SLAM
service's user publish poses (a camera's credentials cannot forge them)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from metricslam.camera import PinholeCamera
from metricslam.errors import ServiceError
from metricslam.slam.system_config import SystemConfig
from metricslam.slam.types import TrackingState
from metricslam.wire import keys
from metricslam.wire.codec import PoseMessage, encode
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.slam_service import SlamService
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import FramePublisher, PoseRecorder, query_health
from metricslam_slam.zenoh_config import ZenohAccess, open_client, pose_acl, session_config

ENDPOINT = "tcp/127.0.0.1:17651"
CAMERA = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=31.5, cy_px=23.5, width_px=64, height_px=48)


def _listening_ips() -> set[str]:
    return {c.laddr.ip for c in psutil.Process().net_connections("tcp") if c.status == psutil.CONN_LISTEN}


def test_peer_sessions_listen_on_loopback_only() -> None:
    router = open_router("tcp/127.0.0.1:17652", access=ZenohAccess())
    peer = open_client("tcp/127.0.0.1:17652", mode="peer", access=ZenohAccess())
    try:
        assert _listening_ips() == {"127.0.0.1"}  # zenoh's own default would add 0.0.0.0 / ::
    finally:
        peer.close()
        router.close()


def test_access_settings_come_from_the_environment(monkeypatch, tmp_path: Path) -> None:
    users = tmp_path / "users.txt"
    users.write_text("slam:s3cret\ncamera:c4m\n")
    monkeypatch.setenv("ZENOH_ACCESS_USERS_FILE", str(users))
    monkeypatch.setenv("ZENOH_ACCESS_POSE_PUBLISHERS", "slam")
    monkeypatch.setenv("ZENOH_ACCESS_PASSWORD", "c4m")
    access = ZenohAccess()
    assert access.pose_publisher_names == ["slam"] and "c4m" not in repr(access)  # a secret
    acl = pose_acl(["slam", "camera"], ["slam"])
    assert acl["subjects"] == [{"id": "not-pose-publishers", "usernames": ["camera"]}]
    assert keys.wildcard("pose") in acl["rules"][0]["key_exprs"]
    with pytest.raises(ServiceError, match="not in the users file"):
        pose_acl(["camera"], ["slam"])
    with pytest.raises(ServiceError, match="USERS_FILE"):
        session_config("router", listen=[ENDPOINT], access=ZenohAccess(pose_publishers="slam", users_file=None))


@pytest.fixture()
def guarded_router(tmp_path: Path):
    users = tmp_path / "users.txt"
    users.write_text("slam:slam-pw\ncamera:camera-pw\nviewer:viewer-pw\n")
    router = open_router(ENDPOINT, access=ZenohAccess(users_file=users, pose_publishers="slam"))
    yield
    router.close()


def _as(user: str, password: str):
    return open_client(ENDPOINT, access=ZenohAccess(user=user, password=password))


def test_wrong_or_missing_credentials_cannot_connect(guarded_router) -> None:
    for user, password in (("camera", "wrong"), ("nobody", "x")):
        with pytest.raises(ServiceError, match="ZENOH_ACCESS_USER"):
            _as(user, password)
    with pytest.raises(ServiceError):
        open_client(ENDPOINT, access=ZenohAccess())
    _as("camera", "camera-pw").close()


def test_only_the_slam_user_publishes_poses(guarded_router, monkeypatch) -> None:
    monkeypatch.setenv("ZENOH_ACCESS_USER", "slam")  # the service reads its credentials from here
    monkeypatch.setenv("ZENOH_ACCESS_PASSWORD", "slam-pw")
    svc = SlamService(SlamServiceSettings(zenoh_endpoint=ENDPOINT, depth_url=None, session_kind="identity",
                                          status_period_s=0.2),
                      config=SystemConfig(depth={"use_scale": False})).start()
    camera, viewer = _as("camera", "camera-pw"), _as("viewer", "viewer-pw")
    try:
        deadline = time.monotonic() + 5
        while query_health(viewer, 0.5) is None and time.monotonic() < deadline:
            time.sleep(0.05)
        recorder = PoseRecorder(viewer, "cam0")
        publisher = FramePublisher(camera, "cam0")
        assert publisher.wait_for_subscriber(10)
        for i in range(3):
            publisher.publish(i, i, np.zeros((48, 64), np.uint8), CAMERA)
        assert recorder.wait_frames(3, 10)  # frames from the camera user, poses from the slam user
        forged = PoseMessage(camera_id="cam0", frame_index=999, t_ns=0, state=TrackingState.TRACKING,
                             T_world_cam=np.eye(4))
        camera.put(keys.key("cam0", "pose"), encode(forged))
        camera.put(keys.key("cam1", "pose"), encode(forged.model_copy(update={"camera_id": "cam1"})))
        other = PoseRecorder(viewer, "cam1")
        time.sleep(0.5)
        camera.put(keys.key("cam1", "pose"), encode(forged.model_copy(update={"camera_id": "cam1"})))
        time.sleep(1.0)
        assert 999 not in recorder.poses and not other.poses  # the router dropped them
        assert svc.health()["cameras"] == ["cam0"]
    finally:
        camera.close()
        viewer.close()
        svc.stop()
