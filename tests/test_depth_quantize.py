"""Static int8 quantization of the depth model: contract kept, precision declared, output close
to float32 on a held-out image, bad inputs refused with actionable messages (CLI included)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from metricslam.datasets._common import load_image
from metricslam.depth import DEFAULT_MODEL_PATH, FLOAT32_MODEL_PATH, DepthModel, ModelContract
from metricslam_cli.main import main
from metricslam.depth.quantize import (
    INT8_STATIC,
    _CalibrationReader,
    compare_models,
    find_images,
    quantize_model,
)
from metricslam.errors import DatasetError, DepthModelError

onnx = pytest.importorskip("onnx", reason="quantization needs onnx: pip install 'metricslam[quantize]'")

#: int8 vs float32 d_frac on a held-out image: median |log(int8 / fp32)| must stay below this (5 %).
MEDIAN_ABS_LOG_RATIO_TOL = 0.05


def _metadata(path) -> dict[str, str]:
    return {p.key: p.value for p in onnx.load(str(path)).metadata_props}


@pytest.fixture(scope="module")
def calib_dir(synth_sequence):
    return synth_sequence(8, seed=5)


@pytest.fixture(scope="module")
def held_out_image(synth_sequence) -> np.ndarray:
    """A frame of another world (other seed): never seen by the calibration."""
    folder = synth_sequence(8, seed=9)
    return load_image(sorted((folder / "image_0").glob("*.png"))[4], color=False)


@pytest.fixture(scope="module")
def int8_model(calib_dir, tmp_path_factory):
    """The shipped float32 model quantized with 6 rendered images, passed as in-memory arrays."""
    arrays = [load_image(p, color=False) for p in find_images([calib_dir])[:6]]
    out = tmp_path_factory.mktemp("int8") / "depth_int8.onnx"
    result = quantize_model(FLOAT32_MODEL_PATH, out, arrays)
    assert result.n_images == 6 and result.out_path == out
    return out


def test_quantized_model_keeps_contract_and_declares_precision(int8_model):
    source, quantized = _metadata(FLOAT32_MODEL_PATH), _metadata(int8_model)
    # every contract key carries over; only the precision changes (a float32 export may declare it)
    assert {k: quantized[k] for k in source if k != "weights_precision"} == \
        {k: v for k, v in source.items() if k != "weights_precision"}
    assert source.get("weights_precision", "float32") == "float32"
    assert quantized["weights_precision"] == INT8_STATIC
    assert quantized["calibration_data"].startswith("6 images")
    settings = json.loads(quantized["quantization"])
    assert settings["quant_format"] == "QDQ" and settings["per_channel"] is True
    model = DepthModel.load(int8_model)
    assert model.contract.weights_precision == INT8_STATIC
    fp32 = DepthModel.load(FLOAT32_MODEL_PATH)
    assert fp32.contract.weights_precision == "float32"
    assert model.contract.model_copy(update={"weights_precision": "float32"}) == fp32.contract


def test_quantized_graph_is_int8_qdq_with_standard_operators_only(int8_model):
    graph = onnx.load(str(int8_model))
    ops = {(node.domain, node.op_type) for node in graph.graph.node}
    assert ("", "QuantizeLinear") in ops and ("", "DequantizeLinear") in ops
    assert {domain for domain, _ in ops} == {""}
    assert {op.domain for op in graph.opset_import} <= {"", "ai.onnx"}
    weights = [t for t in graph.graph.initializer if t.data_type == onnx.TensorProto.INT8]
    fp32_params = DepthModel.load(FLOAT32_MODEL_PATH).contract.params
    assert sum(int(np.prod(t.dims)) for t in weights) > 0.9 * fp32_params
    assert int8_model.stat().st_size < FLOAT32_MODEL_PATH.stat().st_size / 2


def test_int8_inverse_depth_agrees_with_fp32_on_held_out_image(int8_model, held_out_image):
    fx_px = 0.6 * held_out_image.shape[1]
    ref = DepthModel.load(FLOAT32_MODEL_PATH).predict_inv_depth(held_out_image, fx_px).inv_depth_per_m
    got = DepthModel.load(int8_model).predict_inv_depth(held_out_image, fx_px).inv_depth_per_m
    assert got.shape == ref.shape and np.all(got > 0)
    log_ratio = np.abs(np.log(got.astype(np.float64) / ref))
    assert np.median(log_ratio) < MEDIAN_ABS_LOG_RATIO_TOL, np.median(log_ratio)


def test_compare_models_is_zero_for_a_model_against_itself_and_small_for_int8(int8_model, held_out_image):
    fp32 = DepthModel.load(FLOAT32_MODEL_PATH)
    same = compare_models(fp32, fp32, [held_out_image, held_out_image[::-1]])
    assert same.n_images == 2 and same.max == 0.0
    int8 = compare_models(fp32, DepthModel.load(int8_model), [held_out_image])
    assert 0.0 < int8.median <= int8.p95 <= int8.max and int8.median < MEDIAN_ABS_LOG_RATIO_TOL
    with pytest.raises(DepthModelError, match="at least one image"):
        compare_models(fp32, fp32, [])


def test_calibration_reader_preprocesses_files_and_arrays_like_inference(calib_dir):
    model = DepthModel.load(FLOAT32_MODEL_PATH)
    path = find_images([calib_dir])[0]
    image = load_image(path, color=False)
    reader = _CalibrationReader(model, [path, image, np.dstack([image] * 3)])
    batches = [reader.get_next() for _ in range(3)]
    assert reader.get_next() is None and reader.count == 3
    expected = model.preprocess([image])
    for batch in batches:
        np.testing.assert_array_equal(batch[model.contract.input_name], expected)


@pytest.mark.parametrize("value", ["int4", "float16", ""])
def test_unknown_weights_precision_is_refused(int8_model, tmp_path, value):
    graph = onnx.load(str(int8_model))
    onnx.helper.set_model_props(graph, {**_metadata(int8_model), "weights_precision": value})
    bad = tmp_path / "bad.onnx"
    onnx.save(graph, str(bad))
    with pytest.raises(DepthModelError, match=r"weights_precision is .*metricslam quantize"):
        DepthModel.load(bad)


def test_contract_without_weights_precision_key_is_float32():
    meta = DepthModel.load(FLOAT32_MODEL_PATH).contract.to_metadata()
    del meta["weights_precision"]  # a model exported before the key existed
    assert ModelContract.from_metadata(meta).weights_precision == "float32"


def test_quantize_refuses_int8_source_empty_calibration_and_unreadable_image(int8_model, tmp_path, held_out_image):
    out = tmp_path / "out.onnx"
    with pytest.raises(DepthModelError, match="already int8-static"):
        quantize_model(int8_model, out, [held_out_image])
    with pytest.raises(DepthModelError, match="already int8-static.*FLOAT32_MODEL_PATH"):
        quantize_model(DEFAULT_MODEL_PATH, out, [held_out_image])  # the shipped default is the int8 copy
    with pytest.raises(DepthModelError, match="at least one calibration image"):
        quantize_model(FLOAT32_MODEL_PATH, out, [])
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="broken.png.*cannot read image"):
        quantize_model(FLOAT32_MODEL_PATH, out, [held_out_image, broken])
    assert not out.exists()


def test_find_images_layouts_stride_and_cap(tmp_path):
    image = np.zeros((20, 30), np.uint8)
    seq = tmp_path / "seq"
    for sub in ("image_0", "image_1"):
        (seq / sub).mkdir(parents=True)
        for i in range(7):
            cv2.imwrite(str(seq / sub / f"{i:06d}.png"), image)
    flat = tmp_path / "flat"
    flat.mkdir()
    for name in ("b.jpg", "a.png", "notes.txt"):
        (flat / name).write_bytes(b"x")
    left = sorted((seq / "image_0").glob("*.png"))

    assert find_images([seq]) == left  # KITTI layout: the left images only
    assert find_images([flat]) == [flat / "a.png", flat / "b.jpg"]
    assert find_images([seq, flat], stride=3) == left[::3] + [flat / "a.png"]
    assert find_images([str(tmp_path / "se*" / "image_*" / "000000.png")]) == [
        seq / "image_0" / "000000.png", seq / "image_1" / "000000.png"]
    assert find_images([seq], max_images=3) == [left[0], left[3], left[6]]
    for missing in (tmp_path / "absent", tmp_path / "nothing*"):
        with pytest.raises(DatasetError, match="holds no image"):
            find_images([missing])


def test_cli_quantize_writes_a_loadable_model(calib_dir, synth_sequence, tmp_path, capsys):
    out = tmp_path / "cli_int8.onnx"
    held_out = synth_sequence(8, seed=9) / "image_0" / "000004.png"
    assert main(["quantize", str(FLOAT32_MODEL_PATH), "--calib-images", str(calib_dir), "--max-images", "2",
                 "--out", str(out), "--check", str(held_out)]) == 0
    printed = capsys.readouterr().out
    assert "int8-static" in printed and "int8 vs float32 on 1 images: |log(d_int8 / d_fp32)| median" in printed
    contract = DepthModel.load(out).contract
    assert contract.weights_precision == INT8_STATIC
    assert _metadata(out)["calibration_data"] == f"2 images: {(calib_dir / 'image_0').resolve()} (2)"


def test_cli_quantize_refuses_a_folder_without_images(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    out = tmp_path / "never.onnx"
    with pytest.warns(FutureWarning, match="--calib is deprecated.*--calib-images"):  # the former name works
        assert main(["quantize", str(FLOAT32_MODEL_PATH), "--calib", str(empty), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert str(empty) in err and "holds no image" in err and "KITTI sequence folder" in err
    assert not out.exists()


def test_a_canonical_camera_model_quantizes_and_keeps_its_contract(calib_dir, held_out_image, tmp_path):
    """Contract v2: calibration images carry no intrinsics; each is fed as the camera that spans the
    whole input, and the int8 copy keeps the v2 keys and agrees with its float32 source."""
    model = onnx.load(str(FLOAT32_MODEL_PATH))
    meta = _metadata(FLOAT32_MODEL_PATH)
    v1 = ModelContract.from_metadata(meta)
    v2 = v1.model_copy(update={"contract_version": "2", "canonical_fx_px": 296.58, "canonical_fy_px": 489.43,
                               "valid_min_fraction": 0.75})
    del model.metadata_props[:]
    for key, value in v2.to_metadata().items():
        model.metadata_props.add(key=key, value=value)
    src = tmp_path / "v2.onnx"
    onnx.save(model, str(src))
    arrays = [load_image(p, color=False) for p in find_images([calib_dir])[:4]]
    out = tmp_path / "v2_int8.onnx"
    quantize_model(src, out, arrays)
    q = DepthModel.load(out)
    assert q.contract.contract_version == "2" and q.contract.canonical_fx_px == pytest.approx(296.58)
    agreement = compare_models(DepthModel.load(src), q, [held_out_image])
    assert agreement.median < MEDIAN_ABS_LOG_RATIO_TOL


def test_cli_quantize_needs_calibration_images(tmp_path, capsys):
    assert main(["quantize", str(FLOAT32_MODEL_PATH), "--out", str(tmp_path / "never.onnx")]) == 1
    assert "pass --calib-images" in capsys.readouterr().err
