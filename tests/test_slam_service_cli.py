"""CLI adapters against an in-process router + service (real zenoh, real subprocesses):
``camera`` from a video file, ``poses`` in TUM format, ``replay`` refusing to publish into the void,
the HTTP depth client against nothing listening."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from metricslam.errors import DepthSourceError
from metricslam.slam.system_config import SystemConfig
from metricslam.trajectory.io import read_tum
from metricslam_slam.service.http_depth import HttpDepthSource
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.slam_service import SlamService
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import query_health
from metricslam_slam.zenoh_config import open_client

CLI = [sys.executable, "-m", "metricslam_cli.main"]
ENDPOINT = "tcp/127.0.0.1:17460"


@pytest.fixture(scope="module")
def service():
    router = open_router(ENDPOINT)
    svc = SlamService(SlamServiceSettings(zenoh_endpoint=ENDPOINT, depth_url=None, session_kind="identity"),
                      config=SystemConfig(depth={"use_scale": False}, queues={"frames": 64})).start()
    client = open_client(ENDPOINT)
    deadline = time.monotonic() + 5
    while query_health(client, 0.5) is None and time.monotonic() < deadline:
        time.sleep(0.05)
    yield svc
    client.close()
    svc.stop()
    router.close()


def _video(path: Path, n: int) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (160, 120))
    rng = np.random.default_rng(0)
    for _ in range(n):
        writer.write(rng.integers(0, 256, (120, 160, 3), dtype=np.uint8))
    writer.release()
    return path


def test_camera_to_poses_tum(service, tmp_path: Path) -> None:
    video = _video(tmp_path / "clip.avi", 12)
    out = tmp_path / "poses.tum"
    poses = subprocess.Popen(CLI + ["poses", "--zenoh-endpoint", ENDPOINT, "--out", str(out),
                                    "--frames", "12", "--timeout", "60", "--format", "tum",
                                    "--camera-id", "webcam", "--all"],  # identity poses are unscaled
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert poses.stdout.readline().startswith("recording")
    cam = subprocess.run(CLI + ["camera", "--device", str(video), "--zenoh-endpoint", ENDPOINT,
                                "--camera-id", "webcam", "--max-rate", "20", "--fx", "140"],
                         capture_output=True, text=True, timeout=60)
    assert cam.returncode == 0, cam.stderr
    assert "published 12 frames" in cam.stdout
    assert poses.wait(60) == 0, poses.stdout.read()
    t_ns, T = read_tum(out)
    assert T.shape == (12, 4, 4) and np.all(np.diff(t_ns) > 0)


def test_poses_fails_when_frames_are_missing(service, tmp_path: Path) -> None:
    out = subprocess.run(CLI + ["poses", "--zenoh-endpoint", ENDPOINT, "--out", str(tmp_path / "x.txt"),
                                "--frames", "3", "--timeout", "1", "--camera-id", "silent"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 1 and "3 of 3 frames have no pose" in out.stderr


def _kitti_folder(root: Path, n: int = 3) -> Path:
    (root / "image_0").mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), np.full((24, 32), i, np.uint8))
    p0 = "50 0 15.5 0 0 50 11.5 0 0 0 1 0"
    (root / "calib.txt").write_text(f"P0: {p0}\nP1: {p0}\n")
    (root / "times.txt").write_text("".join(f"{i / 10:.6e}\n" for i in range(n)))
    return root


def test_replay_refuses_without_a_service(tmp_path: Path) -> None:
    seq = _kitti_folder(tmp_path / "seq")
    router = open_router("tcp/127.0.0.1:17461")
    try:
        out = subprocess.run(CLI + ["replay", str(seq), "--zenoh-endpoint", "tcp/127.0.0.1:17461",
                                    "--wait", "1"], capture_output=True, text=True, timeout=60)
    finally:
        router.close()
    assert out.returncode == 1 and "no SLAM service answered" in out.stderr, out.stderr


def test_replay_publishes_a_folder(service, tmp_path: Path) -> None:
    from metricslam_slam.tools.client import PoseRecorder

    seq = _kitti_folder(tmp_path / "seq", n=5)
    client = open_client(ENDPOINT)
    recorder = PoseRecorder(client, "folder")
    out = subprocess.run(CLI + ["replay", str(seq), "--zenoh-endpoint", ENDPOINT, "--camera-id", "folder",
                                "--rate", "0", "--no-progress"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert recorder.wait_frames(5, 10) and sorted(recorder.poses) == list(range(5))
    recorder.close()
    client.close()


def test_http_depth_source_reports_unreachable() -> None:
    from metricslam.camera import PinholeCamera

    source = HttpDepthSource("http://127.0.0.1:18299", retries=1, backoff_s=0.01)
    assert source.reachable is None
    camera = PinholeCamera(fx_px=50, fy_px=50, cx_px=15.5, cy_px=11.5, width_px=32, height_px=24)
    with pytest.raises(DepthSourceError, match="failed after 2 attempt"):
        source.inv_depth_map(np.zeros((24, 32), np.uint8), camera)
    assert source.reachable is False and source.last_error
    assert source.probe() is False
    source.close()
