"""The torch-free depth model side: contract, onnxruntime model, sampling, CLI ``depth``."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import onnxruntime as ort
import pytest

from metricslam_cli.main import main
from metricslam.depth import (
    DEFAULT_MODEL_PATH,
    FLOAT32_MODEL_PATH,
    DepthModel,
    ModelContract,
    Normalization,
    sample_map,
)
from metricslam.depth.contract import CONTRACT_VERSION
from metricslam.errors import DepthModelError, ImageError


def _contract(**over) -> ModelContract:
    values = dict(model_id="test", input_height=64, input_width=128, normalization=Normalization(
        scale=1 / 255, mean=0.45, std=0.25), output_height=8, output_width=16, baseline_m=0.54, params=10,
        training_data="synthetic", training_commit="abc", created="2026-01-01T00:00:00+00:00")
    values.update(over)
    return ModelContract(**values)


def test_contract_metadata_round_trip():
    contract = _contract()
    meta = contract.to_metadata()
    assert all(isinstance(v, str) for v in meta.values())
    assert ModelContract.from_metadata(meta) == contract


@pytest.mark.parametrize("key", ["baseline_m", "output_definition", "normalization", "contract_version"])
def test_contract_missing_key_raises(key):
    meta = _contract().to_metadata()
    del meta[key]
    with pytest.raises(DepthModelError, match=key):
        ModelContract.from_metadata(meta)


@pytest.mark.parametrize("key,value,match", [
    ("contract_version", "999", "contract_version"),
    ("output_definition", "depth_m", "output_definition"),
    ("baseline_m", "not json", "baseline_m"),
    ("baseline_m", "-1", "invalid"),
    ("unexpected", "1", None),
])
def test_contract_mismatched_metadata_raises(key, value, match):
    meta = _contract().to_metadata()
    meta[key] = value
    if match is None:  # unknown extra keys are ignored (ONNX tools add their own)
        assert ModelContract.from_metadata(meta).model_id == "test"
        return
    with pytest.raises(DepthModelError, match=match):
        ModelContract.from_metadata(meta)


@pytest.fixture(scope="module")
def shipped() -> DepthModel:
    return DepthModel.load()


def test_shipped_model_contract(shipped):
    c = shipped.contract
    assert c.contract_version == CONTRACT_VERSION
    assert (c.output_height, c.output_width) == (c.input_height // 8, c.input_width // 8)
    assert 0.4 < c.baseline_m < 0.7
    assert "kitti06" not in c.training_data  # KITTI 06 is held out for evaluation


def test_default_model_is_the_int8_copy_of_the_float32_network(shipped):
    fp32 = DepthModel.load(FLOAT32_MODEL_PATH)
    assert DEFAULT_MODEL_PATH != FLOAT32_MODEL_PATH and DEFAULT_MODEL_PATH.is_file()
    assert shipped.contract.weights_precision == "int8-static"
    assert fp32.contract.weights_precision == "float32"
    assert shipped.contract.model_id == fp32.contract.model_id  # the same network, quantized
    assert shipped.contract.model_copy(update={"weights_precision": "float32"}) == fp32.contract
    # its activation ranges were calibrated on training images only, never on an evaluation set
    meta = ort.InferenceSession(str(DEFAULT_MODEL_PATH)).get_modelmeta().custom_metadata_map
    assert meta["calibration_data"] and "sequences/06" not in meta["calibration_data"]
    assert "kitti_raw_lidar" not in meta["calibration_data"]


@pytest.mark.parametrize("shape", [(370, 1226), (375, 1242, 3), (97, 211), (480, 640, 3)])
def test_predict_shapes_and_metric_conversion(shipped, shape):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, size=shape, dtype=np.uint8)
    c = shipped.contract
    d = shipped.predict_d_frac([image, image])
    assert d.shape == (2, c.output_height, c.output_width) and d.dtype == np.float32
    np.testing.assert_array_equal(d[0], d[1])
    fx_px = 0.6 * shape[1]
    result = shipped.predict_inv_depth(image, fx_px)
    assert (result.image_width_px, result.image_height_px) == (shape[1], shape[0])
    expected = d[0].astype(np.float64) * shape[1] / (fx_px * c.baseline_m)
    np.testing.assert_allclose(result.inv_depth_per_m, expected, rtol=1e-5)
    np.testing.assert_allclose(result.depth_m() * result.inv_depth_per_m, 1.0, rtol=1e-5)


def test_gray_and_rgb_of_same_scene_agree(shipped):
    rng = np.random.default_rng(1)
    gray = cv2.GaussianBlur(rng.integers(0, 256, (200, 400), dtype=np.uint8), (5, 5), 0)
    rgb = np.repeat(gray[:, :, None], 3, axis=2)
    np.testing.assert_allclose(shipped.predict_d_frac([gray]), shipped.predict_d_frac([rgb]), atol=1e-6)


def test_bad_images_raise(shipped):
    with pytest.raises(ImageError):
        shipped.predict_d_frac([np.zeros((10, 10), np.float32)])
    with pytest.raises(ImageError):
        shipped.predict_d_frac([np.zeros((10, 10, 4), np.uint8)])
    with pytest.raises(ImageError):
        shipped.predict_d_frac([])


@pytest.mark.parametrize("shipped_path", [DEFAULT_MODEL_PATH, FLOAT32_MODEL_PATH], ids=["int8", "float32"])
def test_load_missing_or_foreign_model_raises(tmp_path, shipped_path):
    with pytest.raises(DepthModelError, match="does not exist"):
        DepthModel.load(tmp_path / "nope.onnx")
    onnx = pytest.importorskip("onnx")
    model = onnx.load(str(shipped_path))
    del model.metadata_props[:]
    bare = tmp_path / "bare.onnx"
    onnx.save(model, str(bare))
    with pytest.raises(DepthModelError, match="lacks"):
        DepthModel.load(bare)


def test_sample_map_hand_values():
    grid = np.array([[0.0, 1.0], [2.0, 3.0]])
    # a 2x2 map over a 4x4 image: cell centres at image pixels 0.5 and 2.5
    uv = np.array([[0.5, 0.5], [2.5, 0.5], [0.5, 2.5], [2.5, 2.5], [1.5, 1.5], [1.5, 0.5], [-5, -5], [9, 9]])
    np.testing.assert_allclose(sample_map(grid, uv, (4, 4)), [0, 1, 2, 3, 1.5, 0.5, 0, 3])
    assert np.isnan(sample_map(grid, np.array([[np.nan, 1.0]]), (4, 4))[0])
    with pytest.raises(ImageError):
        sample_map(np.zeros(3), uv, (4, 4))


def test_sample_map_reproduces_affine_fields():
    rng = np.random.default_rng(2)
    h, w, width_px, height_px = 8, 16, 640, 320
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    u_c, v_c = (jj + 0.5) * width_px / w - 0.5, (ii + 0.5) * height_px / h - 0.5
    field = lambda u, v: 0.3 * u - 0.7 * v + 5.0  # noqa: E731
    uv = np.stack([rng.uniform(u_c.min(), u_c.max(), 200), rng.uniform(v_c.min(), v_c.max(), 200)], 1)
    np.testing.assert_allclose(sample_map(field(u_c, v_c), uv, (width_px, height_px)), field(uv[:, 0], uv[:, 1]),
                               rtol=1e-9, atol=1e-9)


@pytest.mark.slow
def test_torch_and_onnxruntime_agree(tmp_path):
    torch = pytest.importorskip("torch")
    from metricslam_train.export import contract_for, export_onnx
    from metricslam_train.network import PyramidDepthNet

    torch.manual_seed(0)
    net = PyramidDepthNet().eval()
    meta = dict(max_d_frac=0.3, input_height=128, input_width=256, baseline_m=0.54, training_data="none",
                normalization=dict(scale=1 / 255, mean=0.45, std=0.25), model_id="agree")
    path = export_onnx(net, contract_for(net, meta), tmp_path / "m.onnx")
    model = DepthModel.load(path)
    rng = np.random.default_rng(3)
    images = [rng.integers(0, 256, (128, 256), dtype=np.uint8) for _ in range(3)]
    x = model.preprocess(images)
    with torch.no_grad():
        expected = net(torch.from_numpy(x))[0][:, 0].numpy()
    np.testing.assert_allclose(model.predict_d_frac(images), expected, rtol=1e-4, atol=1e-6)


def test_core_depth_import_is_torch_free():
    code = ("import sys, metricslam.depth, metricslam_cli.depth_cmd; "
            "bad = [m for m in ('torch', 'zenoh', 'fastapi', 'httpx') if m in sys.modules]; print(bad)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_cli_depth_writes_metric_depth(tmp_path, shipped):
    rng = np.random.default_rng(4)
    bgr = cv2.GaussianBlur(rng.integers(0, 256, (300, 900, 3), dtype=np.uint8), (3, 3), 0)
    image_path = tmp_path / "img.png"
    cv2.imwrite(str(image_path), bgr)
    out, png = tmp_path / "d.npy", tmp_path / "d.png"
    assert main(["depth", str(image_path), "--fx", "700", "--out", str(out), "--png", str(png)]) == 0
    depth = np.load(out)
    c = shipped.contract
    assert depth.shape == (c.output_height, c.output_width) and depth.dtype == np.float32
    assert np.all(depth > 0)
    assert cv2.imread(str(png)).shape == (300, 900, 3)
    expected = shipped.predict_inv_depth(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), 700.0).depth_m()
    np.testing.assert_allclose(depth, expected, rtol=1e-5)
    assert main(["depth", str(tmp_path / "missing.png"), "--fx", "700", "--out", str(out)]) == 1


def test_cli_depth_on_real_kitti_frame(tmp_path, shared_data, capsys):
    image = shared_data / "kitti_odometry" / "sequences" / "06" / "image_0" / "000000.png"
    out, out_fp32 = tmp_path / "d.npy", tmp_path / "d_fp32.npy"
    assert main(["depth", str(image), "--fx", "707.09", "--out", str(out)]) == 0
    assert "int8-static" in capsys.readouterr().out  # the default model says what it is
    assert main(["depth", str(image), "--fx", "707.09", "--out", str(out_fp32), "--model",
                 str(FLOAT32_MODEL_PATH)]) == 0
    assert "float32" in capsys.readouterr().out
    depth, depth_fp32 = np.load(out), np.load(out_fp32)
    assert np.all(np.isfinite(depth)) and np.all(depth > 0)
    # the int8 default stays close to the float32 network on this held-out frame (~1 % median)
    assert np.median(np.abs(np.log(depth.astype(np.float64) / depth_fp32))) < 0.05
    metadata = json.loads(DepthModel.load().contract.model_dump_json())
    assert metadata["output_definition"] == "disparity_fraction_of_width"
