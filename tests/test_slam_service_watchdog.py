"""The SLAM service's own watchdog (docs/deployment.md, "A hung SLAM service"): a camera stuck on
a frame ends the process with exit 70 (so ``restart: unless-stopped`` / Kubernetes restart it);
while all is well the heartbeat file is fresh, which the liveness probe
``python -m metricslam_slam.supervisor.healthcheck --alive`` checks without touching the router.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from metricslam.camera import PinholeCamera
from metricslam.slam.system_config import SystemConfig
from metricslam_slam.service import watchdog
from metricslam_slam.service.sessions import IdentitySession
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.slam_service import SlamService
from metricslam_slam.service.watchdog import EXIT_HUNG, Watchdog, heartbeat_age_s, write_heartbeat
from metricslam_slam.supervisor import healthcheck
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import FramePublisher
from metricslam_slam.zenoh_config import open_client

CAMERA = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=31.5, cy_px=23.5, width_px=64, height_px=48)


def test_check_names_what_hung_and_writes_the_heartbeat_only_while_healthy(tmp_path: Path) -> None:
    stalls = [("the status loop", 0.0), ("camera cam0", 0.5)]
    beat = tmp_path / "alive"
    dog = Watchdog(2.0, lambda: stalls, heartbeat_file=beat, on_hang=lambda m: None)
    assert dog.check() is None and heartbeat_age_s(beat) < 5
    write_heartbeat(beat, now_s=time.time() - 100)
    stalls[1] = ("camera cam0", 3.0)
    message = dog.check()
    assert message is not None and "camera cam0" in message and "status loop" not in message
    assert heartbeat_age_s(beat) > 99  # not refreshed while hung


def test_a_hang_ends_the_process_with_its_exit_status() -> None:
    code = ("import time\nfrom metricslam_slam.service.watchdog import Watchdog\n"
            "Watchdog(0.2, lambda: [('camera cam0', 1.0)], period_s=0.05).start()\ntime.sleep(20)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == EXIT_HUNG
    assert "camera cam0 made no progress" in out.stderr


def test_liveness_probe_reads_the_heartbeat_not_the_router(tmp_path: Path, monkeypatch, capsys) -> None:
    beat = tmp_path / "alive"
    monkeypatch.setenv("SLAM_ZENOH_ENDPOINT", "tcp/127.0.0.1:1")  # no router anywhere
    assert healthcheck.main(["--alive"]) == 1  # SLAM_HEARTBEAT_FILE unset
    assert "SLAM_HEARTBEAT_FILE" in capsys.readouterr().err
    monkeypatch.setenv("SLAM_HEARTBEAT_FILE", str(beat))
    assert healthcheck.main(["--alive"]) == 1  # no heartbeat yet
    write_heartbeat(beat)
    assert healthcheck.main(["--alive"]) == 0
    write_heartbeat(beat, now_s=time.time() - 60)
    assert healthcheck.main(["--alive", "--max-age", "30"]) == 1
    assert "hung or frozen" in capsys.readouterr().err


class HangingSession(IdentitySession):
    """Blocks on its first frame until ``release`` is set (a deadlock, as the service sees it)."""

    release = threading.Event()

    def process(self, frame):
        self.release.wait(30)
        return super().process(frame)


@pytest.mark.timeout(60)
def test_the_service_detects_a_camera_stuck_on_a_frame(tmp_path: Path, monkeypatch) -> None:
    hangs: list[str] = []
    monkeypatch.setattr(watchdog, "_exit_hung", hangs.append)  # instead of os._exit
    endpoint = "tcp/127.0.0.1:17687"
    router = open_router(endpoint)
    client = open_client(endpoint)
    beat = tmp_path / "alive"
    settings = SlamServiceSettings(zenoh_endpoint=endpoint, depth_url=None, session_kind="identity",
                                   status_period_s=0.1, hang_timeout_s=1.0, heartbeat_file=beat)
    svc = SlamService(settings, session_factory=lambda cid, cam: HangingSession(),
                      config=SystemConfig(depth={"use_scale": False})).start()
    try:
        time.sleep(0.5)
        assert heartbeat_age_s(beat) < 2 and not hangs  # idle is not hung
        pub = FramePublisher(client, "cam0")
        assert pub.wait_for_subscriber(10)
        pub.publish(0, 0, np.zeros((48, 64), np.uint8), CAMERA)
        deadline = time.monotonic() + 10
        while not hangs and time.monotonic() < deadline:
            time.sleep(0.05)
        assert hangs and "camera cam0 made no progress" in hangs[0]
        pub.close()
    finally:
        HangingSession.release.set()
        svc.stop()
        client.close()
        router.close()
