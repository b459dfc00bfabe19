"""Contract version 2 (canonical camera): the metadata rules, and the depth service serving a
toy v2 model (fy/cx/cy honoured, a principal point off the image refused with 422).

The service is started for real on 127.0.0.1:18105 (``tests.depth_service_process``)."""

from __future__ import annotations

import io
import math

import cv2
import httpx
import numpy as np
import pytest

from metricslam.camera import PinholeCamera
from metricslam.depth import CONTRACT_VERSIONS, DepthModel, ModelContract
from metricslam.depth.contract import CANONICAL_FIELDS, DEFAULT_VALID_MIN_FRACTION
from metricslam.errors import DepthModelError
from metricslam_depth.metrics import ServiceMetrics
from metricslam_depth.pipeline import DepthPipeline, Upload
from tests.canonical_toy import expected_inv_depth_per_m, ray_image, toy_contract, write_toy_v2_model
from tests.depth_service_process import ServiceProcess

PORT_V2 = 18105


# ----- contract -----

def test_v2_metadata_round_trip_and_defaults():
    contract = toy_contract(valid_min_fraction=0.75)
    meta = contract.to_metadata()
    assert all(isinstance(v, str) for v in meta.values())
    assert {k: meta[k] for k in CANONICAL_FIELDS} == {
        "canonical_fx_px": "320.0", "canonical_fy_px": "320.0", "valid_min_fraction": "0.75"}
    back = ModelContract.from_metadata(meta)
    assert back == contract and back.uses_canonical_camera
    camera = back.canonical_camera()
    assert (camera.fx_px, camera.fy_px, camera.width_px, camera.height_px) == (320.0, 320.0, 512, 256)
    values = toy_contract().model_dump()
    del values["valid_min_fraction"]  # a v2 contract built without one gets the default
    built = ModelContract(**values)
    assert built.contract_version == "2" and built.valid_min_fraction == DEFAULT_VALID_MIN_FRACTION == 0.5
    assert CONTRACT_VERSIONS == ("1", "2")


def test_v1_metadata_has_no_v2_keys_and_no_canonical_camera():
    v1 = toy_contract().model_copy(update={"contract_version": "1", "canonical_fx_px": None,
                                           "canonical_fy_px": None, "valid_min_fraction": None})
    meta = v1.to_metadata()
    assert not set(CANONICAL_FIELDS) & set(meta)
    back = ModelContract.from_metadata(meta)
    assert back.contract_version == "1" and not back.uses_canonical_camera
    with pytest.raises(DepthModelError, match="no canonical camera"):
        back.canonical_camera()


@pytest.mark.parametrize("key", CANONICAL_FIELDS)
def test_v1_model_with_a_v2_key_is_refused(key):
    meta = toy_contract().to_metadata()
    meta["contract_version"] = "1"
    for other in CANONICAL_FIELDS:
        if other != key:
            del meta[other]
    with pytest.raises(DepthModelError, match=f"version-2 keys \\['{key}'\\]"):
        ModelContract.from_metadata(meta)


@pytest.mark.parametrize("key", CANONICAL_FIELDS)
def test_v2_model_without_a_canonical_key_is_refused(key):
    meta = toy_contract().to_metadata()
    del meta[key]
    with pytest.raises(DepthModelError, match=f"lacks \\['{key}'\\]"):
        ModelContract.from_metadata(meta)


@pytest.mark.parametrize("key,value,match", [
    ("contract_version", "3", "contract_version"),
    ("canonical_fx_px", "-320", "invalid"),
    ("canonical_fy_px", "not json", "canonical_fy_px"),
    ("valid_min_fraction", "1.5", "invalid"),
])
def test_v2_bad_values_are_refused(key, value, match):
    meta = toy_contract().to_metadata()
    meta[key] = value
    with pytest.raises(DepthModelError, match=match):
        ModelContract.from_metadata(meta)


def test_constructor_enforces_the_version_rules():
    with pytest.raises(ValueError, match="contract_version '2' needs"):
        toy_contract(canonical_fy_px=None)
    with pytest.raises(ValueError, match="contract_version '1' has no"):
        toy_contract(contract_version="1")


# ----- service pipeline (in process): JPEG reduced decoding keeps the rays exact -----

@pytest.fixture(scope="module")
def toy_path(tmp_path_factory):
    return write_toy_v2_model(tmp_path_factory.mktemp("toy_v2") / "toy.onnx")


@pytest.fixture(scope="module")
def toy(toy_path) -> DepthModel:
    return DepthModel.load(toy_path)


def _camera(fx, fy, cx, cy, w, h) -> PinholeCamera:
    return PinholeCamera(fx_px=fx, fy_px=fy, cx_px=cx, cy_px=cy, width_px=w, height_px=h)


def _ray_error(inv: np.ndarray, camera: PinholeCamera) -> float:
    h, w = inv.shape
    u = (np.arange(w) + 0.5) * camera.width_px / w - 0.5
    v = (np.arange(h) + 0.5) * camera.height_px / h - 0.5
    xn, yn = np.meshgrid((u - camera.cx_px) / camera.fx_px, (v - camera.cy_px) / camera.fy_px)
    finite = np.isfinite(inv)
    assert finite.mean() > 0.3
    return float(np.abs(inv[finite] / expected_inv_depth_per_m(xn, yn)[finite] - 1).max())


def test_pipeline_reduced_jpeg_decode_keeps_the_camera_exact(toy):
    camera = _camera(2600.0, 2700.0, 1010.0, 530.0, 2001, 1001)  # narrow view: a 1/4 decode suffices
    data = cv2.imencode(".jpg", ray_image(camera), [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    pipeline = DepthPipeline(toy, 10**8, 2**30, ServiceMetrics())
    p = pipeline.predict([Upload(bytearray(data), "image/jpeg")], camera.fx_px, "/v1/disparity",
                         camera.fy_px, camera.cx_px, camera.cy_px)
    assert p.sizes_px == [(2001, 1001)] and p.principal_points_px == [(1010.0, 530.0)]
    assert _ray_error(p.inv_depth_per_m[0], camera) < 0.015
    finite = np.isfinite(p.inv_depth_per_m[0])
    np.testing.assert_allclose(p.d_frac[0][finite], (p.inv_depth_per_m[0] * camera.fx_px * toy.contract.baseline_m
                                                     / 2001)[finite], rtol=1e-5)


# ----- the real service with the toy model -----

@pytest.fixture(scope="module")
def client(toy_path):
    with ServiceProcess(PORT_V2, settings={"model_path": toy_path, "max_batch": 4}) as service:
        with httpx.Client(base_url=service.url, timeout=30.0) as c:
            yield c


def _grid(rows) -> np.ndarray:
    return np.array([[math.nan if v is None else v for v in row] for row in rows], dtype=np.float32)


def test_service_reports_the_v2_contract(client):
    contract = client.get("/v1/model").json()
    assert contract["contract_version"] == "2"
    assert (contract["canonical_fx_px"], contract["canonical_fy_px"], contract["valid_min_fraction"]) == (
        320.0, 320.0, 1.0)


def test_service_honours_fy_cx_cy(client, toy):
    camera = _camera(900.0, 1000.0, 260.0, 150.0, 480, 360)
    png = cv2.imencode(".png", ray_image(camera))[1].tobytes()
    params = {"fx": camera.fx_px, "fy": camera.fy_px, "cx": camera.cx_px, "cy": camera.cy_px}
    r = client.post("/v1/disparity", params=params, content=png, headers={"Content-Type": "image/png"})
    assert r.status_code == 200, r.text
    body = r.json()
    assert (body["fx_px"], body["fy_px"], body["cx_px"], body["cy_px"]) == (900.0, 1000.0, 260.0, 150.0)
    served = _grid(body["inv_depth_per_m"])
    local = toy.predict_inv_depth(ray_image(camera), camera=camera).inv_depth_per_m
    np.testing.assert_array_equal(served, local)  # NaN (null) in the same cells
    assert np.isnan(served).any() and _ray_error(served, camera) < 0.015
    # the same pixels with another principal point are other rays: another answer, the camera's own
    moved = {**params, "cx": 200.0}
    r2 = client.post("/v1/disparity", params=moved, content=png,
                     headers={"Content-Type": "image/png", "Accept": "application/x-npy"})
    assert r2.status_code == 200 and r2.headers["X-Cx-Px"] == "200.0" and r2.headers["X-Fy-Px"] == "1000.0"
    stack = np.load(io.BytesIO(r2.content))
    other = toy.predict_inv_depth(ray_image(camera), camera=camera.model_copy(update={"cx_px": 200.0}))
    np.testing.assert_array_equal(stack[1], other.inv_depth_per_m)
    assert not np.allclose(np.nan_to_num(stack[1]), np.nan_to_num(served))
    # absent fy/cx/cy: fy = fx and the image centre, per image in a batch
    files = [("images", ("a.png", png, "image/png")),
             ("images", ("b.png", cv2.imencode(".png", np.full((101, 200), 128, np.uint8))[1].tobytes(),
                         "image/png"))]
    batch = client.post("/v1/disparity/batch", params={"fx": 500.0}, files=files).json()
    assert batch["fy_px"] == 500.0
    assert [(res["cx_px"], res["cy_px"]) for res in batch["results"]] == [(239.5, 179.5), (99.5, 50.0)]
    default = toy.predict_inv_depth(ray_image(camera), camera=_camera(500.0, 500.0, 239.5, 179.5, 480, 360))
    np.testing.assert_array_equal(_grid(batch["results"][0]["inv_depth_per_m"]), default.inv_depth_per_m)


@pytest.mark.parametrize("params,name", [
    ({"cy": 361}, "cy"), ({"cx": 480.5}, "cx"), ({"cy": -1}, "cy"), ({"cy": "nan"}, "cy"),
    ({"fy": 0}, "fy"), ({"fy": "inf"}, "fy"),
])
def test_service_bad_fy_cx_cy_is_422(client, params, name):
    png = cv2.imencode(".png", np.full((360, 480), 128, np.uint8))[1].tobytes()
    r = client.post("/v1/disparity", params={"fx": 900.0, **params}, content=png,
                    headers={"Content-Type": "image/png"})
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["code"] == "invalid-parameter" and name in body["detail"], body


def test_slam_depth_sources_pass_the_whole_camera(client, toy, toy_path):
    """The SLAM's two depth sources (in-process, and the HTTP client of this service) give the
    v2 model's map for the keyframe's camera, NaN outside its field of view kept."""
    from metricslam.slam.depth_source import OnnxDepthSource
    from metricslam_slam.service.http_depth import HttpDepthSource

    camera = _camera(900.0, 1000.0, 260.0, 150.0, 480, 360)
    image = ray_image(camera)
    expected = toy.predict_inv_depth(image, camera=camera).inv_depth_per_m
    assert np.isnan(expected).any()
    np.testing.assert_array_equal(OnnxDepthSource(toy_path).inv_depth_map(image, camera), expected)
    source = HttpDepthSource(str(client.base_url), retries=0)
    try:
        assert source.probe()
        np.testing.assert_array_equal(source.inv_depth_map(image, camera), expected)
        assert source.upload_size_px is None  # a canonical-camera model warps whole images itself
    finally:
        source.close()
