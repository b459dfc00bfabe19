"""The shipped depth model in onnxruntime (no torch): image -> L3 disparity -> metric inverse depth.

Two copies of the same network ship as package data: :data:`DEFAULT_MODEL_PATH`
(``depth_l3_int8.onnx``, static int8, ~2x faster on CPU, the default everywhere a model is not
named) and :data:`FLOAT32_MODEL_PATH` (``depth_l3.onnx``, the float32 export it was quantized
from; see docs/depth_quantization.md).

Example::

    >>> from metricslam.depth import DepthModel, FLOAT32_MODEL_PATH
    >>> model = DepthModel.load()                      # the shipped int8 depth_l3_int8.onnx
    >>> model.contract.weights_precision
    'int8-static'
    >>> inv = model.predict_inv_depth(image_u8, fx_px=718.9)
    >>> inv.inv_depth_per_m.shape                      # (32, 64) covering the whole image
    >>> fp32 = DepthModel.load(FLOAT32_MODEL_PATH)     # the float32 source, same model_id
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from metricslam.depth.contract import ModelContract
from metricslam.disparity import inv_depth_from_width_fraction
from metricslam.errors import DepthModelError, ImageError

_MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
#: the float32 network shipped as package data (trained without KITTI odometry 06; see
#: docs/depth_model.md): the source of the int8 default and the reference for comparisons.
FLOAT32_MODEL_PATH = _MODELS_DIR / "depth_l3.onnx"
#: the default model: the static int8 copy of :data:`FLOAT32_MODEL_PATH` (same contract and
#: ``model_id``, ``weights_precision = "int8-static"``; docs/depth_quantization.md).
DEFAULT_MODEL_PATH = _MODELS_DIR / "depth_l3_int8.onnx"


@dataclass(frozen=True)
class InvDepthMap:
    """The network's output for one image, on the L3 grid covering the whole image.

    Attributes:
        d_frac: (h, w) float32 left disparity as a fraction of image width (training rig).
        inv_depth_per_m: (h, w) float32 metric inverse depth for the caller's camera, 1/m.
        image_width_px / image_height_px: size of the image the map covers (sample it with
            :func:`metricslam.depth.sample.sample_map` and ``image_size=(W, H)``).
    """

    d_frac: np.ndarray
    inv_depth_per_m: np.ndarray
    image_width_px: int
    image_height_px: int

    def depth_m(self) -> np.ndarray:
        """(h, w) float32 depth in metres (``inf`` where the inverse depth is 0)."""
        with np.errstate(divide="ignore"):
            return (1.0 / self.inv_depth_per_m.astype(np.float64)).astype(np.float32)


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 gray, or (H, W, 3) uint8 RGB -> (H, W) uint8 gray."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ImageError(f"expected a uint8 image, got dtype {img.dtype}: convert to 8-bit first")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.ndim != 2 or img.shape[0] < 2 or img.shape[1] < 2:
        raise ImageError(f"expected an (H, W) gray or (H, W, 3) RGB image, got shape {img.shape}")
    return img


class DepthModel:
    """One onnxruntime session of a metricslam depth model and its :class:`ModelContract`."""

    def __init__(self, session: object, contract: ModelContract) -> None:
        self._session = session
        self.contract = contract

    @classmethod
    def load(cls, path: str | Path | None = None, threads: int = 1) -> "DepthModel":
        """Load an ONNX model (default: the shipped int8 one), checking its metadata against the code.

        Args:
            path: ONNX file; ``None`` for :data:`DEFAULT_MODEL_PATH` (int8; pass
                :data:`FLOAT32_MODEL_PATH` for the float32 network).
            threads: onnxruntime intra-op threads.
        """
        import onnxruntime as ort

        model_path = Path(path) if path is not None else DEFAULT_MODEL_PATH
        if not model_path.is_file():
            raise DepthModelError(f"depth model {model_path} does not exist: pass --model PATH to an ONNX file")
        options = ort.SessionOptions()
        options.intra_op_num_threads = int(threads)
        options.inter_op_num_threads = 1
        try:
            session = ort.InferenceSession(str(model_path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own untyped errors
            raise DepthModelError(f"onnxruntime could not load {model_path}: {exc}") from exc
        contract = ModelContract.from_metadata(dict(session.get_modelmeta().custom_metadata_map))
        inputs = {i.name for i in session.get_inputs()}
        outputs = {o.name for o in session.get_outputs()}
        if contract.input_name not in inputs or contract.output_name not in outputs:
            raise DepthModelError(
                f"{model_path}: metadata names input {contract.input_name!r} / output {contract.output_name!r} "
                f"but the graph has {sorted(inputs)} / {sorted(outputs)}: re-export the model"
            )
        return cls(session, contract)

    def preprocess(self, images: Sequence[np.ndarray]) -> np.ndarray:
        """uint8 images of any size -> (B, 1, H_in, W_in) float32 normalized network input."""
        c = self.contract
        norm = c.normalization
        batch = np.empty((len(images), 1, c.input_height, c.input_width), dtype=np.float32)
        for i, image in enumerate(images):
            gray = to_gray_u8(image)
            resized = cv2.resize(gray, (c.input_width, c.input_height), interpolation=cv2.INTER_AREA)
            batch[i, 0] = (resized.astype(np.float32) * norm.scale - norm.mean) / norm.std
        return batch

    def predict_d_frac(self, images: Sequence[np.ndarray]) -> np.ndarray:
        """(B, h, w) float32 left disparity / image width, for a list of uint8 images (gray or RGB)."""
        if len(images) == 0:
            raise ImageError("predict_d_frac needs at least one image")
        x = self.preprocess(images)
        (out,) = self._session.run([self.contract.output_name], {self.contract.input_name: x})
        return np.asarray(out, dtype=np.float32).reshape(len(images), self.contract.output_height,
                                                          self.contract.output_width)

    def predict_inv_depth(self, image: np.ndarray, fx_px: float) -> InvDepthMap:
        """Metric inverse depth (1/m) on the L3 grid for one image of a camera with focal ``fx_px``.

        ``fx_px`` refers to the image as passed (its own width), not to the network input.
        """
        gray = to_gray_u8(image)
        d_frac = self.predict_d_frac([gray])[0]
        height_px, width_px = gray.shape
        inv = inv_depth_from_width_fraction(d_frac, float(fx_px), float(width_px), self.contract.baseline_m)
        return InvDepthMap(d_frac=d_frac, inv_depth_per_m=inv.astype(np.float32),
                           image_width_px=int(width_px), image_height_px=int(height_px))
