"""Test support: a tiny contract-version-2 ONNX model whose output is known from its input, and
images whose brightness is a known function of the viewing ray.

The toy network is ``AveragePool 8x8 -> Mul(D_FRAC_PER_UNIT)`` on the normalized input (scale
1/255, mean 0, std 1), so an input cell of mean gray ``g`` gives ``d_frac = D_FRAC_PER_UNIT·g/255``.
An image whose gray value is ``ray_brightness(x_n, y_n)`` (``x_n = (u − cx)/fx``, ``y_n = (v −
cy)/fy``) therefore has a known metric inverse depth on every ray, whatever the camera — if, and
only if, the canonical-camera plumbing is exact::

    path = write_toy_v2_model(tmp_path / "toy.onnx")
    image = ray_image(camera)                          # (H, W) uint8
    expected = expected_inv_depth_per_m(x_n, y_n)      # 1/m
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.depth import ModelContract, Normalization

INPUT_HW = (256, 512)
OUTPUT_HW = (32, 64)
CANONICAL_FX_PX = 320.0
CANONICAL_FY_PX = 320.0
BASELINE_M = 0.5
D_FRAC_PER_UNIT = 0.1


def toy_contract(valid_min_fraction: float = 1.0, **over) -> ModelContract:
    """The toy's version-2 contract (``valid_min_fraction`` 1: only fully covered cells count,
    so no cell mixes padding into its average)."""
    values = dict(
        model_id="toy-canonical-avgpool", contract_version="2", input_height=INPUT_HW[0],
        input_width=INPUT_HW[1], normalization=Normalization(scale=1 / 255, mean=0.0, std=1.0),
        output_height=OUTPUT_HW[0], output_width=OUTPUT_HW[1], baseline_m=BASELINE_M, params=0,
        training_data="none (test toy)", training_commit="test", created="2026-01-01T00:00:00+00:00",
        canonical_fx_px=CANONICAL_FX_PX, canonical_fy_px=CANONICAL_FY_PX,
        valid_min_fraction=valid_min_fraction,
    )
    values.update(over)
    return ModelContract(**values)


def write_toy_v2_model(path: Path, contract: ModelContract | None = None) -> Path:
    """Write the toy network (dynamic batch) with ``contract`` (default :func:`toy_contract`)."""
    import onnx
    from onnx import TensorProto, helper

    contract = contract or toy_contract()
    h, w = contract.input_height, contract.input_width
    graph = helper.make_graph(
        [
            helper.make_node("AveragePool", ["image"], ["pooled"], kernel_shape=[8, 8], strides=[8, 8]),
            helper.make_node("Mul", ["pooled", "gain"], ["scaled"]),
            helper.make_node("Reshape", ["scaled", "out_shape"], [contract.output_name]),
        ],
        "toy_canonical",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["batch", 1, h, w])],
        [helper.make_tensor_value_info(contract.output_name, TensorProto.FLOAT,
                                       ["batch", contract.output_height, contract.output_width])],
        initializer=[
            helper.make_tensor("gain", TensorProto.FLOAT, [], [D_FRAC_PER_UNIT]),
            helper.make_tensor("out_shape", TensorProto.INT64, [3],
                               [-1, contract.output_height, contract.output_width]),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    for key, value in contract.to_metadata().items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(model)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path


def ray_brightness(x_n: np.ndarray, y_n: np.ndarray) -> np.ndarray:
    """Gray value (float) seen along the ray with normalized coordinates (x_n, y_n): linear, so
    area averages and bilinear interpolation reproduce it exactly."""
    return 128.0 + 40.0 * np.asarray(x_n) + 50.0 * np.asarray(y_n)


def ray_image(camera: PinholeCamera) -> np.ndarray:
    """(H, W) uint8 image of ``camera`` with :func:`ray_brightness` at every pixel centre."""
    v, u = np.mgrid[0:camera.height_px, 0:camera.width_px].astype(np.float64)
    gray = ray_brightness((u - camera.cx_px) / camera.fx_px, (v - camera.cy_px) / camera.fy_px)
    if gray.min() < 0.5 or gray.max() > 254.5:
        raise ValueError(f"camera {camera} sees rays outside the toy's gray range")
    return np.round(gray).astype(np.uint8)


def expected_inv_depth_per_m(x_n: np.ndarray, y_n: np.ndarray) -> np.ndarray:
    """What the toy model + the v2 conversion must give on the ray (x_n, y_n), 1/m."""
    d_frac = D_FRAC_PER_UNIT * ray_brightness(x_n, y_n) / 255.0
    return d_frac * INPUT_HW[1] / (CANONICAL_FX_PX * BASELINE_M)
