"""Issue #19 item 4: ``metricslam replay`` counts the frames the SLAM service confirmed (a pose
each) and exits non-zero, with the counts, when they differ from what it sent — unless
``--allow-loss``. The service here is a stand-in on a real router that answers health queries
and publishes a pose (and a status) for every other frame only, as a service dropping frames from
a full queue would."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from metricslam.errors import ServiceError
from metricslam.slam.types import TrackingState
from metricslam.wire import keys
from metricslam.wire.codec import FrameMessage, PoseMessage, StatusMessage, decode_as, encode
from metricslam_slam.supervisor.launcher import free_port
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import FramePublisher
from metricslam_slam.tools.soak import soak
from metricslam_slam.zenoh_config import open_client

CLI = [sys.executable, "-m", "metricslam_cli.main"]
N_FRAMES = 8


class DroppingService:
    """Health queryable + a pose for each frame whose index ``keep(index)`` accepts."""

    def __init__(self, endpoint: str, keep) -> None:
        self.session = open_client(endpoint)
        self.keep = keep
        self.received = 0
        self._lock = threading.Lock()
        self._entities = [
            self.session.declare_queryable(keys.HEALTH_KEY, lambda q: q.reply(
                keys.HEALTH_KEY, json.dumps({"ready": True}).encode())),
            self.session.declare_subscriber(keys.wildcard("frame"), self._on_frame),
        ]

    def _on_frame(self, sample) -> None:
        msg = decode_as(sample.payload.to_bytes(), FrameMessage)
        with self._lock:
            self.received += 1
            received = self.received
        cam = msg.camera_id
        if self.keep(msg.frame_index):
            self.session.put(keys.key(cam, "pose"), encode(PoseMessage(
                camera_id=cam, frame_index=msg.frame_index, t_ns=msg.t_ns,
                state=TrackingState.TRACKING, T_world_cam=np.eye(4))))
        processed = sum(1 for i in range(msg.frame_index + 1) if self.keep(i))
        self.session.put(keys.key(cam, "status"), encode(StatusMessage(
            camera_id=cam, t_ns=time.time_ns(), frames_received=received,
            frames_processed=processed, queue_drops=received - processed, malformed=0,
            queue_depth=0, fps=0.0)))

    def close(self) -> None:
        for entity in self._entities:
            entity.undeclare()
        self.session.close()


@pytest.fixture()
def router_endpoint():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    yield endpoint
    router.close()


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("replay") / "seq"
    (root / "image_0").mkdir(parents=True)
    for i in range(N_FRAMES):
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), np.full((24, 32), i, np.uint8))
    p0 = "50 0 15.5 0 0 50 11.5 0 0 0 1 0"
    (root / "calib.txt").write_text(f"P0: {p0}\nP1: {p0}\n")
    (root / "times.txt").write_text("".join(f"{i / 10:.6e}\n" for i in range(N_FRAMES)))
    return root


def _replay(endpoint: str, folder: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + ["replay", str(folder), "--zenoh-endpoint", endpoint, "--rate", "0",
                                 "--no-progress", "--confirm-timeout", "2", "--wait", "10", *extra],
                          capture_output=True, text=True, timeout=120)


def test_replay_exits_nonzero_with_the_counts_when_frames_are_lost(router_endpoint, folder) -> None:
    service = DroppingService(router_endpoint, keep=lambda i: i % 2 == 0)
    try:
        out = _replay(router_endpoint, folder)
        allowed = _replay(router_endpoint, folder, "--allow-loss")
    finally:
        service.close()
    assert out.returncode == 1, out.stdout + out.stderr
    assert f"sent {N_FRAMES} frames" in out.stderr and f"confirmed {N_FRAMES // 2}" in out.stderr, out.stderr
    assert "frames [1, 3, 5, 7]" in out.stderr, out.stderr
    assert "dropped from a full queue" in out.stderr, out.stderr  # the service's own counters
    assert allowed.returncode == 0, allowed.stderr
    assert f"confirmed {N_FRAMES // 2}" in allowed.stdout


def test_replay_exits_zero_when_every_frame_is_confirmed(router_endpoint, folder) -> None:
    service = DroppingService(router_endpoint, keep=lambda i: True)
    try:
        out = _replay(router_endpoint, folder)
    finally:
        service.close()
    assert out.returncode == 0, out.stdout + out.stderr
    assert f"sent {N_FRAMES} frames" in out.stdout and f"confirmed {N_FRAMES} " in out.stdout, out.stdout


def test_a_frame_publisher_knows_when_a_service_subscribes(router_endpoint) -> None:
    """``wait_for_subscriber`` is zenoh's matching status: false with no SLAM service on the
    router, true once one subscribes (the puts before that would have been dropped)."""
    client = open_client(router_endpoint)
    publisher = FramePublisher(client, "cam0")
    try:
        assert publisher.wait_for_subscriber(0.3) is False
        service = DroppingService(router_endpoint, keep=lambda i: True)
        try:
            assert publisher.wait_for_subscriber(10) is True
        finally:
            service.close()
    finally:
        publisher.close()
        client.close()


@pytest.mark.parametrize("with_service", [False, True])
def test_a_soak_stops_with_the_reason_instead_of_waiting_out_every_frame(router_endpoint, folder,
                                                                         with_service) -> None:
    """No service: the soak says so at once. A service that loses frame 3: the soak stops after
    one pose timeout, naming the frame and the service's counters (it used to wait the timeout on
    every later frame, past pytest's limit)."""
    service = DroppingService(router_endpoint, keep=lambda i: i != 3) if with_service else None
    client = open_client(router_endpoint)
    t0 = time.monotonic()
    try:
        with pytest.raises(ServiceError) as err:
            soak(client, folder, "cam0", 40, os.getpid(), pose_timeout_s=1.0)
    finally:
        client.close()
        if service is not None:
            service.close()
    assert time.monotonic() - t0 < 10
    if with_service:
        assert "frames [3]" in str(err.value) and "dropped from a full queue" in str(err.value)
    else:
        assert "no SLAM service subscribed" in str(err.value)
