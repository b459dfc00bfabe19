"""Torch-free depth inference: the ONNX model contract, the canonical camera (contract v2),
onnxruntime model, map sampling."""

from metricslam.depth.canonical import CanonicalCamera, CanonicalWarp, canonical_warp
from metricslam.depth.contract import (
    CANONICAL_CONTRACT_VERSION,
    CONTRACT_VERSION,
    CONTRACT_VERSIONS,
    OUTPUT_DEFINITION,
    ModelContract,
    Normalization,
)
from metricslam.depth.model import (
    DEFAULT_MODEL_PATH,
    FLOAT32_MODEL_PATH,
    RENDERED_MODEL_PATH,
    DepthModel,
    InvDepthMap,
)
from metricslam.depth.sample import sample_map

__all__ = [
    "CANONICAL_CONTRACT_VERSION",
    "CONTRACT_VERSION",
    "CONTRACT_VERSIONS",
    "CanonicalCamera",
    "CanonicalWarp",
    "canonical_warp",
    "OUTPUT_DEFINITION",
    "DEFAULT_MODEL_PATH",
    "FLOAT32_MODEL_PATH",
    "RENDERED_MODEL_PATH",
    "DepthModel",
    "InvDepthMap",
    "ModelContract",
    "Normalization",
    "sample_map",
]
