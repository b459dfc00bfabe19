"""HttpDepthSource against a frozen depth service (accepts connections, never answers: SIGSTOP)."""

from __future__ import annotations

import socket
import threading

import numpy as np
import pytest

from metricslam.camera import PinholeCamera
from metricslam.errors import DepthSourceError
from metricslam_slam.service.http_depth import HttpDepthSource

CAMERA = PinholeCamera(fx_px=700.0, fy_px=700.0, cx_px=63.5, cy_px=31.5, width_px=128, height_px=64)


class FrozenServer:
    """A listening socket on 127.0.0.1 that accepts and counts connections and never replies."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.port = self.sock.getsockname()[1]
        self.accepted = 0
        self.conns: list[socket.socket] = []
        self._stop = False
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        self.sock.settimeout(0.05)
        while not self._stop:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            self.accepted += 1
            self.conns.append(conn)

    def close(self) -> None:
        self._stop = True
        self.thread.join()
        for c in self.conns:
            c.close()
        self.sock.close()


@pytest.fixture
def frozen():
    server = FrozenServer()
    yield server
    server.close()


def test_a_known_down_service_gets_one_short_attempt_per_keyframe(frozen):
    source = HttpDepthSource(f"http://127.0.0.1:{frozen.port}", timeout_s=0.3, retries=2, backoff_s=0.01,
                             down_timeout_s=0.1)
    image = np.zeros((64, 128), np.uint8)
    with pytest.raises(DepthSourceError, match="3 attempt"):
        source.inv_depth_map(image, CAMERA)
    assert source.reachable is False and frozen.accepted == 3
    with pytest.raises(DepthSourceError, match="known down: one short attempt"):
        source.inv_depth_map(image, CAMERA)
    assert frozen.accepted == 4  # one more connection, not three
    assert source.requests_failed == 2 and source.outages == 1
    source.close()
