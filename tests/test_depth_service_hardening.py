"""Abuse of the depth service, started for real on 127.0.0.1:18110-18111 (issue #19 hardening).

Each test reproduces one measured failure of the unhardened service and fails on it: idle and
slow connections starving /healthz, bodies buffered before being judged, pixel bombs decoded,
implausible fx accepted, internals leaked in answers. Small limits and short timeouts keep the
whole file well under 20 s.
"""

from __future__ import annotations

import re
import socket
import struct
import time
import zlib

import cv2
import httpx
import numpy as np
import pytest

from metricslam_depth.imaging import check_header
from metricslam_depth.errors import RequestProblem
from tests.depth_service_process import ServiceProcess

PORT_HARD, PORT_BROKEN = 18110, 18111
FX_PX = 718.856
MAX_BODY_BYTES = 256 * 1024
MAX_BATCH = 4
BATCH_LIMIT_BYTES = MAX_BODY_BYTES * MAX_BATCH + 64 * 1024
HEADER_TIMEOUT_S = 1.0
MAX_CONNECTIONS = 64
SETTINGS = {
    "max_body_bytes": MAX_BODY_BYTES, "max_batch": MAX_BATCH, "max_connections": MAX_CONNECTIONS,
    "max_inflight_requests": 8, "header_timeout_s": HEADER_TIMEOUT_S, "keep_alive_timeout_s": 1.0,
    "body_timeout_s": 1.5, "body_budget_wait_s": 0.5, "max_header_bytes": 8192,
    "max_buffered_body_bytes": 2 * BATCH_LIMIT_BYTES, "retry_after_s": 2,
}
PNG = cv2.imencode(".png", np.random.default_rng(0).integers(0, 255, (120, 200), np.uint8))[1].tobytes()


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def _png_bomb(width: int = 4096, height: int = 4096) -> bytes:
    """A real, valid ~130 kB PNG of zeros declaring ``width x height`` 16-bit RGBA (128 MiB decoded)."""
    deflate = zlib.compressobj(9)
    row = bytes(1 + width * 8)
    idat = b"".join(deflate.compress(row) for _ in range(height)) + deflate.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 6, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


@pytest.fixture(scope="module")
def service():
    with ServiceProcess(PORT_HARD, settings=SETTINGS) as svc:
        yield svc


@pytest.fixture(scope="module")
def client(service):
    with httpx.Client(base_url=service.url, timeout=10.0) as c:
        yield c


def _connect(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=5.0)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def _closed_by_server(sock: socket.socket, wait_s: float) -> bool:
    """True once the server closed ``sock`` (EOF or reset) within ``wait_s``; data is drained."""
    sock.settimeout(wait_s)
    deadline = time.monotonic() + wait_s
    try:
        while time.monotonic() < deadline:
            if sock.recv(65536) == b"":
                return True
    except (TimeoutError, socket.timeout):
        return False
    except OSError:
        return True
    return False


def _read_response(sock: socket.socket, wait_s: float = 3.0) -> tuple[int, bytes]:
    """(status, raw head + body) of the first response on ``sock`` (bodies with Content-Length)."""
    sock.settimeout(wait_s)
    data = b""
    while True:
        head, sep, body = data.partition(b"\r\n\r\n")
        length = re.search(rb"content-length: *(\d+)", head.lower())
        if sep and (length is None or len(body) >= int(length.group(1))):
            break
        chunk = sock.recv(65536)
        if not chunk:
            break
        data += chunk
    return int(data.split(b" ", 2)[1]), data


def _health_ms(url: str) -> tuple[int, float]:
    t0 = time.perf_counter()
    with httpx.Client(timeout=5.0) as fresh:
        status = fresh.get(url + "/healthz").status_code
    return status, (time.perf_counter() - t0) * 1e3


def _post(client: httpx.Client, body: bytes, fx: object = FX_PX) -> httpx.Response:
    return client.post("/v1/disparity", params={"fx": fx}, content=body, headers={"Content-Type": "image/png"})


def _problem(r: httpx.Response, status: int, code: str) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    assert body["code"] == code, body
    return body


# ----- 8: idle and slow connections -----

def test_idle_sockets_beyond_the_connection_cap_do_not_starve_health(service, client):
    idle = [_connect(service.port) for _ in range(300)]
    slow = [_connect(service.port) for _ in range(20)]
    for sock in slow:  # slowloris: a request head that never ends
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: ")
    try:
        for _ in range(5):
            status, ms = _health_ms(service.url)
            assert status == 200 and ms < 1000, (status, ms)
        assert _post(client, PNG).status_code == 200
        # the server holds at most max_connections: the oldest idle sockets were closed for the new
        closed = sum(_closed_by_server(s, 0.01) for s in idle[:100])
        assert closed >= 90, closed
        # and every idle or slow one is gone once the request-head deadline has passed
        time.sleep(HEADER_TIMEOUT_S + 0.3)
        assert all(_closed_by_server(s, 0.5) for s in idle[-40:] + slow)
    finally:
        for sock in idle + slow:
            sock.close()


def test_request_head_deadline_and_size_limit(service):
    silent = _connect(service.port)
    t0 = time.monotonic()
    assert _closed_by_server(silent, HEADER_TIMEOUT_S + 2.0)
    assert time.monotonic() - t0 < HEADER_TIMEOUT_S + 1.0
    silent.close()
    # a keep-alive connection that starts a second request and stalls is closed too
    with _connect(service.port) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        assert _read_response(sock)[0] == 200
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHo")
        assert _closed_by_server(sock, HEADER_TIMEOUT_S + 2.0)
    with _connect(service.port) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 20_000 + b"\r\n\r\n")
        status, raw = _read_response(sock)
        assert status == 431 and b"connection: close" in raw.lower()


def test_too_many_requests_in_flight_is_503_but_health_still_answers(service, client):
    # 8 uploads that declare a small body and never send it hold every in-flight slot
    stalled = [_connect(service.port) for _ in range(8)]
    for sock in stalled:
        sock.sendall(b"POST /v1/disparity?fx=700 HTTP/1.1\r\nHost: x\r\nContent-Type: image/png\r\n"
                     b"Content-Length: 1000\r\n\r\n")
    time.sleep(0.2)
    try:
        body = _problem(_post(client, PNG), 503, "busy")
        assert "retry" in body["detail"]
        assert client.get("/healthz").status_code == 200 and client.get("/readyz").status_code == 200
        # the stalled bodies run into body_timeout_s: 408, connection closed, slots free again
        for sock in stalled:
            assert _read_response(sock, 3.0)[0] == 408
    finally:
        for sock in stalled:
            sock.close()
    assert _post(client, PNG).status_code == 200


# ----- 9: bodies judged before they are buffered -----

def test_declared_oversized_body_is_413_before_any_byte_is_read(service):
    with _connect(service.port) as sock:
        sock.sendall(b"POST /v1/disparity?fx=700 HTTP/1.1\r\nHost: x\r\nContent-Type: image/png\r\n"
                     b"Content-Length: 10737418240\r\n\r\n")  # 10 GiB announced, none sent
        status, raw = _read_response(sock, 2.0)
        assert status == 413 and b"connection: close" in raw.lower()
        assert _closed_by_server(sock, 2.0)


def test_oversized_batch_part_is_413_while_it_streams(service):
    """One image part over max_body_bytes inside a batch under the batch limit: refused at once,
    while the client is still sending (the rest of the batch is never sent)."""
    head = (b"--b\r\nContent-Disposition: form-data; name=images; filename=a.png\r\n"
            b"Content-Type: image/png\r\n\r\n")
    with _connect(service.port) as sock:
        sock.sendall(b"POST /v1/disparity/batch?fx=700 HTTP/1.1\r\nHost: x\r\n"
                     b"Content-Type: multipart/form-data; boundary=b\r\n"
                     b"Content-Length: %d\r\n\r\n" % (BATCH_LIMIT_BYTES - 1000) + head)
        sock.sendall(PNG[:100] + bytes(MAX_BODY_BYTES + 1000))
        status, raw = _read_response(sock, 2.0)
        assert status == 413, raw
        assert b"images[0]" in raw and b"connection: close" in raw.lower()


def test_chunked_body_over_the_limit_is_413_while_it_streams(service):
    with _connect(service.port) as sock:
        sock.sendall(b"POST /v1/disparity?fx=700 HTTP/1.1\r\nHost: x\r\nContent-Type: image/png\r\n"
                     b"Transfer-Encoding: chunked\r\n\r\n")
        block = bytes(64 * 1024)
        for _ in range(MAX_BODY_BYTES // len(block) + 2):  # never the terminating 0-chunk
            sock.sendall(b"%x\r\n" % len(block) + block + b"\r\n")
        assert _read_response(sock, 2.0)[0] == 413


def test_upload_memory_budget_makes_extra_uploads_wait_then_503(service, client):
    # two batches that declare the whole batch limit and send slowly hold the whole budget
    holders = [_connect(service.port) for _ in range(2)]
    for sock in holders:
        sock.sendall(b"POST /v1/disparity/batch?fx=700 HTTP/1.1\r\nHost: x\r\n"
                     b"Content-Type: multipart/form-data; boundary=b\r\n"
                     b"Content-Length: %d\r\n\r\n--b\r\n" % BATCH_LIMIT_BYTES)
    time.sleep(0.2)
    try:
        t0 = time.monotonic()
        r = _post(client, PNG)
        body = _problem(r, 503, "upload-budget")
        assert 0.4 < time.monotonic() - t0 < 2.0 and r.headers["retry-after"] == "2"
        assert "upload" in body["detail"]
    finally:
        for sock in holders:
            sock.close()
    time.sleep(0.2)
    assert _post(client, PNG).status_code == 200  # budget released by the closed uploads


# ----- 10: pixel bombs refused from the header -----

def _decode_count(client: httpx.Client) -> float:
    for line in client.get("/metrics").text.splitlines():
        if line.startswith("depth_decode_seconds_count"):
            return float(line.split()[-1])
    return 0.0


def test_png_bomb_is_refused_from_its_header_before_decoding(client):
    bomb = _png_bomb()
    assert len(bomb) < 200_000  # 130 kB on the wire, 128 MiB decoded
    decoded_before = _decode_count(client)
    t0 = time.perf_counter()
    body = _problem(_post(client, bomb), 413, "image-too-large")
    assert (time.perf_counter() - t0) < 0.2  # decoding it costs ~0.5 s of CPU
    assert "16 bits" in body["detail"] and "4 channels" in body["detail"]
    files = [("images", ("a.png", PNG, "image/png")), ("images", ("b.png", bomb, "image/png"))]
    body = _problem(client.post("/v1/disparity/batch", params={"fx": FX_PX}, files=files), 413, "image-too-large")
    assert body["detail"].startswith("image 1:")
    assert _decode_count(client) == decoded_before  # no decoder ran for either request


def _jpeg_header(width: int, height: int, components: int, precision: int = 8) -> bytes:
    sof = struct.pack(">BHHB", precision, height, width, components) + b"\x01\x11\x00" * components
    return b"\xff\xd8" + b"\xff\xc0" + struct.pack(">H", 2 + len(sof)) + sof


def test_decoded_size_counts_channels_and_bit_depth():
    ok = _jpeg_header(4096, 2048, 1)
    assert check_header(ok, "image/jpeg", 4096 * 4096, 8 * 2**20).decoded_bytes == 4096 * 2048
    for data in (_jpeg_header(4096, 2048, 3), _jpeg_header(4096, 2048, 1, precision=12)):
        with pytest.raises(RequestProblem) as info:
            check_header(data, "image/jpeg", 4096 * 4096, 8 * 2**20)
        assert info.value.status == 413
    assert check_header(_png_bomb(64, 64), "image/png", 10**6, 10**6).decoded_bytes == 64 * 64 * 8


# ----- 13: implausible intrinsics -----

@pytest.mark.parametrize("fx", ["1e9", "1e6", "200000", "nan", "NaN", "inf", "-inf", "1e308", "0", "-1"])
def test_implausible_fx_is_422_with_the_plausible_range(client, fx):
    body = _problem(_post(client, PNG, fx=fx), 422, "invalid-parameter")
    assert "fx" in body["detail"] and "100000" in body["detail"], body["detail"]


def test_fx_at_the_bounds_is_accepted(client):
    assert _post(client, PNG, fx="100000").status_code == 200
    assert _post(client, PNG, fx="0.001").status_code == 200


# ----- 14: no internals in answers -----

_EXCEPTION_NAME = re.compile(r"\b[A-Z][A-Za-z]*(Error|Exception)\b|Traceback")


def _assert_discloses_nothing(text: str, *secrets: str) -> None:
    assert not _EXCEPTION_NAME.search(text), text
    for secret in ("/tmp", "/work", "/home", "site-packages", ".onnx", ".py", *secrets):
        assert secret not in text, (secret, text)


def test_model_contract_has_no_paths(client):
    contract = client.get("/v1/model").json()
    assert "/" not in contract["training_data"] and contract["training_data"]


def test_parser_errors_do_not_echo_exception_text(client):
    r = client.post("/v1/disparity/batch", params={"fx": FX_PX}, content=b"--x\r\nga\x00rbage\r\n--x--",
                    headers={"Content-Type": "multipart/form-data; boundary=zz"})
    assert r.status_code == 400
    _assert_discloses_nothing(r.text)
    assert "character" not in r.json()["detail"]  # python-multipart's own wording stays in the log


def test_failed_model_load_reveals_no_path_or_exception(tmp_path):
    broken = tmp_path / "secret_dir" / "broken.onnx"
    broken.parent.mkdir()
    broken.write_bytes(b"not an onnx file")
    with ServiceProcess(PORT_BROKEN, settings={"model_path": broken}, wait_ready=False) as svc:
        with httpx.Client(base_url=svc.url, timeout=10.0) as c:
            deadline = time.monotonic() + 20
            while "failed" not in c.get("/readyz").text and time.monotonic() < deadline:
                time.sleep(0.1)
            answers = [c.get("/readyz"), c.get("/v1/model"), _post(c, PNG)]
            assert [r.status_code for r in answers] == [503, 503, 503]
            assert "failed to load" in answers[0].json()["detail"]
            for r in answers:
                _assert_discloses_nothing(r.text, "secret_dir", "broken", str(tmp_path))
