"""HttpDepthSource against a frozen depth service (accepts connections, never answers: SIGSTOP),
an older one (no PGM uploads), and what it uploads."""

from __future__ import annotations

import socket
import threading

import numpy as np
import pytest

from metricslam.camera import PinholeCamera
from metricslam.errors import DepthSourceError
from metricslam.depth.model import to_gray_u8
from metricslam_slam.service.http_depth import HttpDepthSource, encode_pgm

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


class OldDepthService:
    """A real HTTP server on 127.0.0.1 that answers like a depth service from before PGM
    uploads: 415 for ``image/x-portable-graymap``, a valid ``.npy`` stack for ``image/png``."""

    def __init__(self) -> None:
        import io
        from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

        stack = np.full((2, 4, 8), 0.05, np.float32)
        buf = io.BytesIO()
        np.save(buf, stack)
        answer = buf.getvalue()
        self.media_types: list[str] = []
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 (http.server's name)
                self.rfile.read(int(self.headers["Content-Length"]))
                media = self.headers["Content-Type"]
                outer.media_types.append(media)
                status, body = (200, answer) if media == "image/png" else (415, b'{"title": "Unsupported"}')
                self.send_response(status)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args: object) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def test_keyframes_go_as_pgm_and_fall_back_to_png_once_for_an_older_service():
    old = OldDepthService()
    try:
        source = HttpDepthSource(f"http://127.0.0.1:{old.port}", timeout_s=2.0)
        image = np.random.default_rng(0).integers(0, 255, (64, 128), dtype=np.uint8)
        for _ in range(3):
            inv_depth = source.inv_depth_map(image, CAMERA)
            assert inv_depth.shape == (4, 8) and np.allclose(inv_depth, 0.05)
        # one PGM attempt, refused with 415, then PNG for that keyframe and every later one
        assert old.media_types == ["image/x-portable-graymap", "image/png", "image/png", "image/png"]
        assert source.requests_ok == 3 and source.requests_failed == 0
        source.close()
    finally:
        old.close()


def test_pgm_upload_is_the_gray_pixels_behind_a_p5_header():
    rgb = np.random.default_rng(1).integers(0, 255, (5, 7, 3), dtype=np.uint8)
    data = encode_pgm(rgb)
    header = b"P5\n7 5\n255\n"
    assert data.startswith(header)
    gray = np.frombuffer(data[len(header):], np.uint8).reshape(5, 7)
    np.testing.assert_array_equal(gray, to_gray_u8(rgb))
    with pytest.raises(Exception, match="uint8"):
        encode_pgm(rgb.astype(np.float32))
