"""The default endpoints agree: a bare ``metricslam depth-service`` and a bare ``metricslam
slam-service`` find each other and the SLAM service gets learned scale; a SLAM service whose
depth service is dead says so — logged once, on ``…/status``, counted — and keeps tracking.

Real processes on loopback: uvicorn on 127.0.0.1, a zenoh router with an explicit endpoint.
When the default depth port is taken on this machine, both services are moved to a free port
through their own environment variables (``DEPTH_PORT`` / ``SLAM_DEPTH_URL``), the way an
operator would."""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest

from metricslam.camera import PinholeCamera
from metricslam.datasets import open_sequence
from metricslam.endpoints import DEFAULT_DEPTH_URL, depth_url
from metricslam.slam.system_config import SystemConfig
from metricslam_depth.settings import DepthServiceSettings
from metricslam_slam.service.sessions import IdentitySession
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.slam_service import SlamService
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import FramePublisher, PoseRecorder, query_health
from metricslam_slam.zenoh_config import open_client

from child_process import interrupt_and_wait

CLI = [sys.executable, "-m", "metricslam_cli.main"]
ENDPOINT = "tcp/127.0.0.1:17480"
DEAD_ENDPOINT = "tcp/127.0.0.1:17485"
OUR_ENV = ("DEPTH_HOST", "DEPTH_PORT", "SLAM_DEPTH_URL", "SLAM_ZENOH_ENDPOINT", "METRICSLAM_CONFIG")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _port_taken(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _start(args: list[str], env: dict, log_path) -> subprocess.Popen:
    """A child whose output goes to ``log_path`` (a pipe nobody reads could fill and stall it)."""
    with open(log_path, "w") as log:
        return subprocess.Popen(CLI + args, env=env, stdout=log, stderr=subprocess.STDOUT, text=True)


def _stop(proc: subprocess.Popen, log_path) -> str:
    """SIGINT (then SIGKILL), and the child's output."""
    interrupt_and_wait(proc)
    return log_path.read_text()


def test_default_urls_agree(monkeypatch) -> None:
    for name in OUR_ENV:
        monkeypatch.delenv(name, raising=False)
    depth = DepthServiceSettings()
    assert SlamServiceSettings().depth_url == depth_url(depth.host, depth.port) == DEFAULT_DEPTH_URL


@pytest.mark.slow
def test_bare_depth_and_slam_services_find_each_other(synth_sequence, tmp_path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in OUR_ENV and not k.startswith("METRICSLAM_")}
    env.update(PYTHONUNBUFFERED="1", METRICSLAM_VO__PRESET="synth")  # rendered 620x188 frames
    url = DEFAULT_DEPTH_URL
    if _port_taken(DepthServiceSettings().port):  # someone else's: move both sides, by env
        port = _free_port()
        env.update(DEPTH_PORT=str(port), SLAM_DEPTH_URL=depth_url(port=port))
        url = depth_url(port=port)
    seq = open_sequence(synth_sequence(60, seed=3, path="loop"))
    router = open_router(ENDPOINT)
    depth_log, slam_log = tmp_path / "depth.log", tmp_path / "slam.log"
    depth = _start(["depth-service"], env, depth_log)
    slam = None
    client = open_client(ENDPOINT)
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert depth.poll() is None, depth_log.read_text()
            time.sleep(0.3)
        else:
            pytest.fail(f"depth service not ready at {url}: {depth_log.read_text()}")
        slam = _start(["slam-service", "--zenoh-endpoint", ENDPOINT], env, slam_log)
        while query_health(client, 0.5) is None and time.monotonic() < deadline:
            assert slam.poll() is None, slam_log.read_text()
            time.sleep(0.1)
        recorder = PoseRecorder(client, "cam0")
        publisher = FramePublisher(client, "cam0")
        assert publisher.wait_for_subscriber(10)
        for i in range(len(seq)):  # lock step: the queue never drops a frame
            frame = seq[i]
            publisher.publish(frame.index, frame.t_ns, frame.image, frame.camera)
            assert recorder.wait_for(lambda r, i=i: i in r.poses, 30), f"no pose for frame {i}"

        def scale_factors(r: PoseRecorder) -> int:
            status = r.latest_status()
            return 0 if status is None else status.session_stats.get("backend.scale_factors", 0)

        assert recorder.wait_for(lambda r: scale_factors(r) > 0, 60), recorder.latest_status()
        status = recorder.latest_status()
        assert status.depth_url == url and status.depth_reachable is True
        assert status.depth_outages == 0 and status.depth_error is None
        assert query_health(client)["depth_reachable"] is True
        recorder.close()
        publisher.close()
    finally:
        client.close()
        slam_output = _stop(slam, slam_log) if slam is not None else ""
        _stop(depth, depth_log)
        router.close()
    assert "NOT reachable" not in slam_output, slam_output
    assert f"learned scale factors from the depth service at {url}" in slam_output, slam_output


def test_dead_depth_url_is_logged_once_reported_and_counted(caplog) -> None:
    dead_url = depth_url(port=_free_port())  # nothing listens there
    camera = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=31.5, cy_px=23.5, width_px=64, height_px=48)
    router = open_router(DEAD_ENDPOINT)
    client = open_client(DEAD_ENDPOINT)
    settings = SlamServiceSettings(zenoh_endpoint=DEAD_ENDPOINT, depth_url=dead_url, status_period_s=0.2,
                                   depth_retries=0)
    caplog.set_level(logging.INFO)
    service = SlamService(settings, session_factory=lambda cid, cam: IdentitySession(),
                          config=SystemConfig()).start()
    try:
        recorder = PoseRecorder(client, "cam0")
        publisher = FramePublisher(client, "cam0")
        deadline = time.monotonic() + 10
        while query_health(client, 0.5) is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert publisher.wait_for_subscriber(10)
        for i in range(5):
            publisher.publish(i, i, np.full((48, 64), 40 * i, np.uint8), camera)
        assert recorder.wait_frames(5, 10)  # tracking goes on without depth
        assert recorder.wait_for(lambda r: len(r.statuses) >= 5, 10)  # several failed probes
        status = recorder.latest_status()
        assert status.depth_url == dead_url and status.depth_reachable is False
        assert status.depth_error and status.depth_outages == 1  # one outage, however many probes
        health = query_health(client)
        assert health["depth_reachable"] is False and health["depth_outages"] == 1
        recorder.close()
        publisher.close()
    finally:
        client.close()
        service.stop()
        router.close()
    loud = [r for r in caplog.records if "NOT reachable" in r.getMessage()]
    assert len(loud) == 1 and loud[0].levelno == logging.ERROR, [r.getMessage() for r in loud]
    assert dead_url in loud[0].getMessage()


def test_retired_service_variables_are_refused(monkeypatch) -> None:
    from metricslam.errors import ConfigError

    monkeypatch.setenv("SLAM_USE_SCALE", "false")  # once a setting; now the system config's
    with pytest.raises(ConfigError, match="METRICSLAM_DEPTH__USE_SCALE"):
        SlamService(SlamServiceSettings(depth_url=None), config=SystemConfig())
