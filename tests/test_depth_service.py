"""The depth service, started for real (``metricslam depth-service`` child processes on
127.0.0.1:18100-18199) and spoken to over HTTP with httpx.

Covers: every documented status code, JSON vs ``.npy`` agreement, batch, readiness, Prometheus
counters, admission control (429 / 503 with Retry-After), and the image header sniffing.
Validity flags (``valid: false``) and ``Accept`` / 406: ``tests/test_depth_service_validity.py``.
"""

from __future__ import annotations

import io
import struct
import zlib
from concurrent.futures import ThreadPoolExecutor

import cv2
import httpx
import numpy as np
import pytest

from metricslam.depth import DepthModel
from metricslam.errors import ConfigError
from metricslam_depth.disclosure import public_contract
from metricslam_depth.settings import load_settings
from tests.depth_service_process import ServiceProcess

PORT_MAIN, PORT_UNREADY, PORT_OVERLOAD = 18101, 18102, 18103
FX_PX = 718.856
SMALL_BODY_LIMIT = 64 * 1024


def _image(width: int, height: int, seed: int = 0) -> np.ndarray:
    """A gray test image with structure (gradient + blobs), deterministic per seed."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width]
    img = 80 + 100 * (y / height) + 20 * np.sin(x / 17.0)
    for _ in range(6):
        cx, cy, r = rng.integers(0, width), rng.integers(0, height), rng.integers(5, 40)
        img[(x - cx) ** 2 + (y - cy) ** 2 < r * r] = rng.integers(0, 255)
    return np.clip(img, 0, 255).astype(np.uint8)


def _png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


def _jpeg(image: np.ndarray) -> bytes:
    return cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()


def _png_header_only(width: int, height: int) -> bytes:
    """A PNG signature + IHDR claiming ``width x height`` and nothing else (a bomb's header)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr
    return b"\x89PNG\r\n\x1a\n" + chunk + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))


IMG = _image(1226, 370)
PNG = _png(IMG)


@pytest.fixture(scope="module")
def service():
    with ServiceProcess(PORT_MAIN, settings={"max_body_bytes": SMALL_BODY_LIMIT * 16, "max_batch": 4}) as svc:
        yield svc


@pytest.fixture(scope="module")
def client(service):
    with httpx.Client(base_url=service.url, timeout=30.0) as c:
        yield c


@pytest.fixture(scope="module")
def model() -> DepthModel:
    return DepthModel.load(threads=1)


def _post(client, body: bytes, content_type: str | None = "image/png", fx: object = FX_PX, **kw):
    headers = dict(kw.pop("headers", {}))
    if content_type is not None:
        headers["Content-Type"] = content_type
    params = {} if fx is None else {"fx": fx}
    return client.post("/v1/disparity", content=body, params=params, headers=headers, **kw)


def _assert_problem(response: httpx.Response, status: int, code: str | None = None) -> dict:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    body = response.json()
    assert body["status"] == status
    assert body["type"].startswith("urn:metricslam:problem:")
    assert len(body["detail"]) > 20  # says what to fix, not just "bad request"
    if code is not None:
        assert body["code"] == code, body
    return body


def _metric(client, name: str, **labels: str) -> float:
    """Value of one sample of /metrics (0 if absent)."""
    text = client.get("/metrics").text
    want = ",".join(f'{k}="{v}"' for k, v in sorted(labels.items()))
    for line in text.splitlines():
        if line.startswith("#") or not line.startswith(name):
            continue
        series, value = line.rsplit(" ", 1)
        got = series[len(name):].strip("{}")
        if ",".join(sorted(got.split(","))) == want or (not labels and got == ""):
            return float(value)
    return 0.0


# ----- happy paths -----

def test_health_ready_and_model_contract(client, model):
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200 and ready.json()["ready"] is True
    contract = client.get("/v1/model").json()
    # the ONNX file's contract, less the training machine's paths (test_depth_service_hardening)
    assert contract == public_contract(model.contract).model_dump(mode="json")
    assert ready.json()["model_id"] == contract["model_id"]
    # with no model named the service runs the shipped default, the int8 copy of the network
    assert ready.json()["weights_precision"] == contract["weights_precision"] == "int8-static"


def test_json_answer_matches_in_process_model_and_metric_formula(client, model):
    r = _post(client, PNG)
    assert r.status_code == 200, r.text
    body = r.json()
    c = model.contract
    assert body["model_id"] == c.model_id and body["baseline_m"] == c.baseline_m
    assert (body["image_width_px"], body["image_height_px"]) == (1226, 370)
    assert body["shape"] == [c.output_height, c.output_width]
    d_frac = np.asarray(body["d_frac"], dtype=np.float32)
    inv = np.asarray(body["inv_depth_per_m"], dtype=np.float32)
    assert d_frac.shape == inv.shape == (c.output_height, c.output_width)
    expected = model.predict_d_frac([IMG])[0]
    np.testing.assert_allclose(d_frac, expected, rtol=1e-4, atol=1e-6)
    metric = np.where(d_frac > 0, d_frac.astype(np.float64) * 1226 / (FX_PX * c.baseline_m), 0.0)
    np.testing.assert_allclose(inv, metric, rtol=1e-6)
    assert body["inference_ms"] > 0


def test_npy_answer_equals_json_answer(client):
    as_json = _post(client, PNG).json()
    r = _post(client, PNG, headers={"Accept": "application/x-npy"})
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-npy"
    stack = np.load(io.BytesIO(r.content), allow_pickle=False)
    assert stack.dtype == np.float32 and stack.shape == (2, *as_json["shape"])
    np.testing.assert_allclose(stack[0], np.asarray(as_json["d_frac"], np.float32), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(stack[1], np.asarray(as_json["inv_depth_per_m"], np.float32), rtol=1e-5)
    assert r.headers["x-model-id"] == as_json["model_id"]
    assert float(r.headers["x-fx-px"]) == FX_PX
    assert int(r.headers["x-image-width-px"]) == 1226 and int(r.headers["x-image-height-px"]) == 370


def test_jpeg_and_colour_input_are_accepted(client):
    colour = cv2.merge([IMG, IMG, IMG])
    for body, ctype in [(_jpeg(IMG), "image/jpeg"), (_png(colour), "image/png"), (_jpeg(IMG), "image/jpg")]:
        r = _post(client, body, ctype)
        assert r.status_code == 200, r.text
    # gray and its 3-channel copy are the same picture -> the same answer
    gray, rgb = _post(client, PNG).json(), _post(client, _png(colour)).json()
    np.testing.assert_allclose(gray["d_frac"], rgb["d_frac"], rtol=1e-5, atol=1e-7)


def _pgm(image: np.ndarray, max_value: int = 255, comment: bytes = b"") -> bytes:
    height, width = image.shape
    raster = image.astype(">u2" if max_value > 255 else np.uint8).tobytes()
    return b"P5\n" + comment + b"%d %d\n%d\n" % (width, height, max_value) + raster


def test_binary_pgm_is_the_same_picture_as_png(client):
    """The fast path (the SLAM service's keyframes): gray pixels as they are, no inflate."""
    png = _post(client, PNG, headers={"Accept": "application/x-npy"})
    for ctype in ("image/x-portable-graymap", "image/x-pgm"):
        pgm = _post(client, _pgm(IMG, comment=b"# a comment line\n"), ctype, headers={"Accept": "application/x-npy"})
        assert pgm.status_code == 200, pgm.text
        assert pgm.content == png.content  # bit for bit: the network sees the same pixels
        assert int(pgm.headers["x-image-width-px"]) == 1226


def test_slam_client_uploads_v1_keyframes_at_the_network_input_with_the_same_answer(client):
    """HttpDepthSource resizes a keyframe to a version-1 model's input (INTER_AREA, intrinsics
    scaled) before uploading it: the answer equals the one for the full image."""
    from metricslam.camera import PinholeCamera
    from metricslam_slam.service.http_depth import HttpDepthSource

    camera = PinholeCamera(fx_px=FX_PX, fy_px=FX_PX, cx_px=601.9, cy_px=183.1, width_px=1226, height_px=370)
    full = np.asarray(_post(client, PNG).json()["inv_depth_per_m"], np.float32)
    source = HttpDepthSource(str(client.base_url), retries=0)
    try:
        np.testing.assert_allclose(source.inv_depth_map(IMG, camera), full, rtol=1e-5)  # before it knows
        assert source.upload_size_px is None
        np.testing.assert_allclose(source.inv_depth_map(IMG, camera), full, rtol=1e-5)  # resized
        assert source.upload_size_px == (512, 256)
        small = IMG[:200, :400]  # smaller than the input: sent as it is
        cam_small = camera.model_copy(update={"width_px": 400, "height_px": 200, "cx_px": 199.5, "cy_px": 99.5})
        as_is = np.asarray(_post(client, _png(small)).json()["inv_depth_per_m"], np.float32)
        np.testing.assert_allclose(source.inv_depth_map(small, cam_small), as_is, rtol=1e-5)
    finally:
        source.close()


def test_inverse_depth_scales_with_fx_and_width(client):
    a = _post(client, PNG, fx=FX_PX).json()
    b = _post(client, PNG, fx=2 * FX_PX).json()
    np.testing.assert_allclose(np.asarray(b["inv_depth_per_m"]) * 2, a["inv_depth_per_m"], rtol=1e-5)
    np.testing.assert_allclose(b["d_frac"], a["d_frac"], rtol=1e-6)


def test_batch_parts_without_filename_are_images(client):
    boundary = "b0undary"
    body = b"".join(
        f"--{boundary}\r\nContent-Disposition: form-data; name=images\r\nContent-Type: image/png\r\n\r\n".encode()
        + PNG + b"\r\n" for _ in range(2)
    ) + f"--{boundary}--\r\n".encode()
    r = client.post("/v1/disparity/batch", params={"fx": FX_PX}, content=body,
                    headers={"Content-Type": f"multipart/form-data; boundary={boundary}"})
    assert r.status_code == 200, r.text
    assert len(r.json()["results"]) == 2


def test_batch_matches_single_requests_json_and_npy(client):
    images = [_image(1226, 370, 1), _image(640, 200, 2), _image(300, 300, 3)]
    files = [("images", ("a.png", _png(images[0]), "image/png")),
             ("images", ("b.jpg", _jpeg(images[1]), "image/jpeg")),
             ("images", ("c.png", _png(images[2]), "image/png"))]
    r = client.post("/v1/disparity/batch", params={"fx": FX_PX}, files=files)
    assert r.status_code == 200, r.text
    results = r.json()["results"]
    assert [(x["image_width_px"], x["image_height_px"]) for x in results] == [(1226, 370), (640, 200), (300, 300)]
    for (_, (_, data, ctype)), result in zip(files, results):
        single = _post(client, data, ctype).json()
        np.testing.assert_allclose(result["d_frac"], single["d_frac"], rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(result["inv_depth_per_m"], single["inv_depth_per_m"], rtol=1e-4, atol=1e-6)
    rb = client.post("/v1/disparity/batch", params={"fx": FX_PX}, files=files,
                     headers={"Accept": "application/x-npy"})
    stack = np.load(io.BytesIO(rb.content), allow_pickle=False)
    assert stack.shape == (3, 2, *results[0]["shape"])
    assert rb.headers["x-image-width-px"] == "1226,640,300"
    for i, result in enumerate(results):
        np.testing.assert_allclose(stack[i, 1], result["inv_depth_per_m"], rtol=1e-4, atol=1e-6)


# ----- bad input never becomes a 5xx -----

@pytest.mark.parametrize(
    ("body", "ctype", "code"),
    [
        (b"", "image/png", "undecodable-image"),
        (b"definitely not an image", "image/png", "undecodable-image"),
        (PNG[: len(PNG) // 2], "image/png", "undecodable-image"),
        (PNG[:40], "image/png", "undecodable-image"),
        (_jpeg(IMG)[:-500], "image/jpeg", "undecodable-image"),
        (PNG, "image/jpeg", "undecodable-image"),  # declared type does not match the bytes
        (_png_header_only(0, 10), "image/png", "undecodable-image"),
        (b"P2\n4 4\n255\n" + b"0 " * 16, "image/x-portable-graymap", "undecodable-image"),  # ASCII PGM
        (b"P5\n1226 370\n255\n" + bytes(1000), "image/x-portable-graymap", "undecodable-image"),  # short raster
        (b"P5\n1226 370\n", "image/x-portable-graymap", "undecodable-image"),  # no maxval
        (PNG, "image/x-portable-graymap", "undecodable-image"),
    ],
)
def test_undecodable_images_are_400(client, body, ctype, code):
    _assert_problem(_post(client, body, ctype), 400, code)


@pytest.mark.parametrize("ctype", ["text/plain", "image/gif", "application/octet-stream", None])
def test_unsupported_media_type_is_415(client, ctype):
    body = _assert_problem(_post(client, PNG, ctype), 415, "unsupported-media-type")
    assert "image/png" in body["detail"] and "image/x-portable-graymap" in body["detail"]


def test_too_large_is_413(client):
    limit = SMALL_BODY_LIMIT * 16
    _assert_problem(_post(client, b"\x89PNG" + bytes(limit)), 413, "body-too-large")

    def chunks():  # no Content-Length: the limit must hold while streaming too
        for _ in range(20):
            yield bytes(limit // 10)

    _assert_problem(_post(client, chunks()), 413, "body-too-large")
    _assert_problem(_post(client, _png_header_only(100_000, 100_000)), 413, "image-too-large")
    files = [("images", (f"{i}.png", PNG, "image/png")) for i in range(5)]  # max_batch is 4
    _assert_problem(client.post("/v1/disparity/batch", params={"fx": FX_PX}, files=files), 413, "too-many-images")


@pytest.mark.parametrize("fx", [None, -718.0, 0, "nan", "inf", "-inf", "abc", "", 1e12])
def test_bad_fx_is_422(client, fx):
    body = _assert_problem(_post(client, PNG, fx=fx), 422, "invalid-parameter")
    assert "fx" in body["detail"]


def test_bad_batch_bodies_are_4xx(client):
    url, params = "/v1/disparity/batch", {"fx": FX_PX}
    _assert_problem(client.post(url, params=params, content=PNG, headers={"Content-Type": "image/png"}), 415)
    _assert_problem(client.post(url, params=params, content=b"--x\r\ngarbage",
                                headers={"Content-Type": "multipart/form-data"}), 400, "bad-multipart")
    _assert_problem(client.post(url, params=params, content=b"--x\r\ngarbage",  # unterminated: no parts
                                headers={"Content-Type": "multipart/form-data; boundary=x"}), 422)
    _assert_problem(client.post(url, params=params, files=[("other", ("a.png", PNG, "image/png"))]), 422)
    _assert_problem(client.post(url, params=params, data={"images": "text"},  # part without a type
                                files=[("x", ("a.png", PNG, "image/png"))]), 415)
    bad = [("images", ("a.png", PNG, "image/png")), ("images", ("b.png", PNG[:100], "image/png"))]
    body = _assert_problem(client.post(url, params=params, files=bad), 400, "undecodable-image")
    assert body["detail"].startswith("image 1:")
    _assert_problem(client.post(url, params=params, files=[("images", ("a.gif", PNG, "image/gif"))]), 415)


def test_unknown_routes_and_methods_are_problem_bodies(client):
    _assert_problem(client.get("/v2/nothing"), 404, "not-found")
    _assert_problem(client.put("/v1/disparity"), 405, "method-not-allowed")


def test_metrics_counters_move(client):
    ok_before = _metric(client, "depth_requests_total", route="/v1/disparity", method="POST", status="200")
    bad_before = _metric(client, "depth_requests_total", route="/v1/disparity", method="POST", status="400")
    infer_before = _metric(client, "depth_inference_seconds_count", route="/v1/disparity")
    for _ in range(3):
        assert _post(client, PNG).status_code == 200
    assert _post(client, b"junk").status_code == 400
    assert _metric(client, "depth_requests_total", route="/v1/disparity", method="POST", status="200") == ok_before + 3
    assert _metric(client, "depth_requests_total", route="/v1/disparity", method="POST", status="400") == bad_before + 1
    assert _metric(client, "depth_inference_seconds_count", route="/v1/disparity") == infer_before + 3
    assert _metric(client, "depth_model_loaded") == 1.0
    assert _metric(client, "depth_queue_depth") == 0.0
    client.get("/scanner/probe/1")
    assert 'route="/scanner' not in client.get("/metrics").text  # unknown paths are not labels


def test_openapi_documents_every_error_status(client):
    spec = client.get("/openapi.json").json()
    for path in ("/v1/disparity", "/v1/disparity/batch"):
        op = spec["paths"][path]["post"]
        assert {"200", "400", "413", "415", "422", "429", "503"} <= set(op["responses"])
        assert "application/x-npy" in op["responses"]["200"]["content"]
        assert "requestBody" in op


# ----- readiness and overload (own service instances) -----

def test_unloadable_model_keeps_service_unready_with_reason(tmp_path):
    broken = tmp_path / "broken.onnx"
    broken.write_bytes(b"not an onnx file")
    with ServiceProcess(PORT_UNREADY, settings={"model_path": broken, "retry_after_s": 7}, wait_ready=False) as svc:
        with httpx.Client(base_url=svc.url, timeout=10.0) as c:
            assert c.get("/healthz").status_code == 200
            ready = c.get("/readyz")
            assert ready.status_code == 503 and ready.json()["ready"] is False
            assert "failed to load" in ready.json()["detail"]
            r = _post(c, PNG)
            body = _assert_problem(r, 503, "not-ready")
            assert r.headers["retry-after"] == "7" and "model" in body["detail"]
            _assert_problem(c.get("/v1/model"), 503, "not-ready")
            _assert_problem(_post(c, PNG, fx=-1), 422)  # bad input is still the caller's problem


@pytest.mark.slow
def test_overload_is_refused_with_retry_after_not_queued_forever():
    big = _png(np.random.default_rng(0).integers(0, 255, (1024, 2048), dtype=np.uint8))
    files = [("images", (f"{i}.png", big, "image/png")) for i in range(8)]
    settings_ = {"max_concurrency": 1, "max_queue": 2, "request_timeout_s": 0.05, "threads": 1,
                 "retry_after_s": 3}
    with ServiceProcess(PORT_OVERLOAD, settings=settings_) as svc:
        def call(_: int) -> httpx.Response:
            with httpx.Client(base_url=svc.url, timeout=60.0) as c:
                return c.post("/v1/disparity/batch", params={"fx": FX_PX}, files=files)

        with ThreadPoolExecutor(12) as pool:
            responses = list(pool.map(call, range(12)))
        statuses = sorted(r.status_code for r in responses)
        assert set(statuses) <= {200, 429, 503}, statuses
        assert 200 in statuses and 429 in statuses and 503 in statuses, statuses
        for r in responses:
            if r.status_code != 200:
                assert r.headers["retry-after"] == "3"
                _assert_problem(r, r.status_code, "overloaded" if r.status_code == 429 else "queue-timeout")
        with httpx.Client(base_url=svc.url) as c:
            assert _metric(c, "depth_rejected_total", reason="queue_full") == statuses.count(429)
            assert _metric(c, "depth_rejected_total", reason="queue_timeout") == statuses.count(503)
            assert _metric(c, "depth_inflight") == 0 and _metric(c, "depth_queue_depth") == 0
            assert _post(c, PNG).status_code == 200  # recovers once the burst is over


def test_pgm_header_bomb_is_413_before_any_pixel_is_read(client):
    bomb = b"P5\n100000 100000\n65535\n" + bytes(64)  # declares 20 GB of 16-bit pixels
    _assert_problem(_post(client, bomb, "image/x-portable-graymap"), 413, "image-too-large")


def test_settings_come_from_environment_and_refuse_bad_values(monkeypatch):
    monkeypatch.setenv("DEPTH_MAX_QUEUE", "3")
    assert load_settings(port=18199).max_queue == 3
    monkeypatch.setenv("DEPTH_MAX_QUEUE", "lots")
    with pytest.raises(ConfigError, match="DEPTH_MAX_QUEUE"):
        load_settings()
