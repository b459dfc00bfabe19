"""Torch-free depth inference: the ONNX model contract, onnxruntime model, map sampling."""

from metricslam.depth.contract import CONTRACT_VERSION, OUTPUT_DEFINITION, ModelContract, Normalization
from metricslam.depth.model import DEFAULT_MODEL_PATH, FLOAT32_MODEL_PATH, DepthModel, InvDepthMap
from metricslam.depth.sample import sample_map

__all__ = [
    "CONTRACT_VERSION",
    "OUTPUT_DEFINITION",
    "DEFAULT_MODEL_PATH",
    "FLOAT32_MODEL_PATH",
    "DepthModel",
    "InvDepthMap",
    "ModelContract",
    "Normalization",
    "sample_map",
]
