"""The depth service's answer validity and content negotiation, started for real (a
``metricslam depth-service`` child process on 127.0.0.1:18106) and spoken to over HTTP with httpx.

Covers: flat / empty images answered but flagged ``valid: false`` (JSON and ``X-Valid``, single
and batch), ``Accept`` negotiation (406 when neither JSON nor ``.npy`` is acceptable), and the SLAM
side's depth sources refusing flat keyframes (no scale factor from a flagged map).
Request helpers are shared with ``tests/test_depth_service.py``.
"""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from tests.depth_service_process import ServiceProcess
from tests.test_depth_service import FX_PX, IMG, PNG, SMALL_BODY_LIMIT, _assert_problem, _png, _post

PORT_VALIDITY = 18106


@pytest.fixture(scope="module")
def service():
    with ServiceProcess(PORT_VALIDITY, settings={"max_body_bytes": SMALL_BODY_LIMIT * 16, "max_batch": 4}) as svc:
        yield svc


@pytest.fixture(scope="module")
def client(service):
    with httpx.Client(base_url=service.url, timeout=30.0) as c:
        yield c


# ----- validity of the answer, content negotiation -----

@pytest.mark.parametrize("pixels", [np.zeros((370, 1226), np.uint8), np.full((370, 1226), 200, np.uint8)],
                         ids=["black", "uniform"])
def test_flat_image_is_answered_but_flagged_invalid(client, pixels):
    """A blank or uniform image gets the network's output, but flagged: no confident map."""
    r = _post(client, _png(pixels))
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["valid"] is False and "flat image" in body["invalid_reason"]
    npy = _post(client, _png(pixels), headers={"Accept": "application/x-npy"})
    assert npy.headers["x-valid"] == "0"
    ok = _post(client, PNG).json()
    assert ok["valid"] is True and ok["invalid_reason"] is None
    assert _post(client, PNG, headers={"Accept": "application/x-npy"}).headers["x-valid"] == "1"


def test_batch_flags_each_image(client):
    files = [("images", ("a.png", PNG, "image/png")), ("images", ("b.png", _png(np.zeros((370, 1226), np.uint8)),
                                                                   "image/png"))]
    r = client.post("/v1/disparity/batch", params={"fx": FX_PX}, files=files)
    assert r.status_code == 200, r.text
    assert [res["valid"] for res in r.json()["results"]] == [True, False]
    r = client.post("/v1/disparity/batch", params={"fx": FX_PX}, files=files,
                    headers={"Accept": "application/x-npy"})
    assert r.headers["x-valid"] == "1,0"


@pytest.mark.parametrize("accept", ["text/html", "text/html, application/xhtml+xml", "application/json;q=0, text/plain"])
def test_accept_without_json_or_npy_is_406(client, accept):
    body = _assert_problem(_post(client, PNG, headers={"Accept": accept}), 406, "not-acceptable")
    assert "application/json" in body["detail"]
    files = [("images", ("a.png", PNG, "image/png"))]
    r = client.post("/v1/disparity/batch", params={"fx": FX_PX}, files=files, headers={"Accept": accept})
    _assert_problem(r, 406, "not-acceptable")


@pytest.mark.parametrize(("accept", "media"), [
    ("*/*", "application/json"), ("application/*", "application/json"),
    ("text/html,application/xhtml+xml,application/xml;q=0.9,*/*;q=0.8", "application/json"),  # a browser's
    ("application/x-npy", "application/x-npy"), ("application/x-npy;q=0, application/json", "application/json"),
])
def test_accept_ranges_that_admit_an_answer(client, accept, media):
    r = _post(client, PNG, headers={"Accept": accept})
    assert r.status_code == 200 and r.headers["content-type"] == media


# ----- the SLAM side never turns a flagged map into a scale factor -----

def test_slam_depth_sources_refuse_flat_images(client):
    """A flat keyframe gets no learned scale, whether depth comes from the service (its
    ``X-Valid: 0`` answer) or from the in-process model (the same check); a real view still works."""
    from metricslam.camera import PinholeCamera
    from metricslam.depth import DEFAULT_MODEL_PATH
    from metricslam.errors import DepthSourceError
    from metricslam.slam.depth_source import OnnxDepthSource
    from metricslam_slam.service.http_depth import HttpDepthSource

    camera = PinholeCamera(fx_px=FX_PX, fy_px=FX_PX, cx_px=612.5, cy_px=184.5, width_px=1226, height_px=370)
    flat = np.full((370, 1226), 17, np.uint8)
    real = IMG
    http = HttpDepthSource(str(client.base_url), retries=0)
    try:
        with pytest.raises(DepthSourceError, match="flagged its image invalid"):
            http.inv_depth_map(flat, camera)
        assert http.requests_invalid == 1 and http.reachable is True and http.requests_ok == 0
        assert np.isfinite(http.inv_depth_map(real, camera)).any() and http.requests_ok == 1
    finally:
        http.close()
    local = OnnxDepthSource(DEFAULT_MODEL_PATH)
    with pytest.raises(DepthSourceError, match="flat image"):
        local.inv_depth_map(flat, camera)
    assert np.isfinite(local.inv_depth_map(real, camera)).any()

