"""Static int8 quantization of a metricslam depth model (onnxruntime's quantizer).

Weights are quantized per output channel to signed int8, activations to unsigned int8 with
ranges calibrated (min/max) on images preprocessed exactly as :meth:`DepthModel.preprocess` does
at inference. The result is an ONNX file that :meth:`DepthModel.load` runs like the float32
one; it carries the source's whole :class:`~metricslam.depth.contract.ModelContract` plus
``weights_precision = "int8-static"``, ``calibration_data`` (which images, how many) and
``quantization`` (JSON: tool and settings).

Format: **QDQ** (QuantizeLinear/DequantizeLinear pairs around float operators) by default. It
uses only standard ONNX operators, so the file loads in any ONNX runtime, and onnxruntime's CPU
provider fuses the pairs into its int8 kernels when it builds the session. QOperator writes
onnxruntime contrib operators (``com.microsoft`` QLinearAdd, QLinearConcat, ...) that only
onnxruntime runs; it is kept as an option but measured no faster on this network (see
``docs/depth_quantization.md``).

Calibration images must come from the model's **training** data (for the shipped models KITTI
01/03 and ``runs/synth_train`` worlds), never from an evaluation set (KITTI 06,
``kitti_raw_lidar``): ranges fitted on the test images would leak them into the model.

Needs the ``onnx`` package (``pip install 'metricslam[quantize]'``), imported only when called.

Example::

    >>> from metricslam.depth.quantize import quantize_model
    >>> result = quantize_model("depth_l3.onnx", "depth_l3_int8.onnx", ["a.png", "b.png"])
    >>> result.n_images, result.contract.weights_precision
    (2, 'int8-static')
"""

from __future__ import annotations

import glob
import json
import tempfile
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from metricslam.camera import PinholeCamera
from metricslam.datasets import load_image
from metricslam.depth.contract import FLOAT32, INT8_STATIC, ModelContract
from metricslam.depth.model import DepthModel
from metricslam.errors import DatasetError, DepthModelError, MetricSlamError

CalibImage = str | Path | np.ndarray
#: file suffixes taken as images when a calibration folder is listed.
IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff"})


class QuantizeConfig(BaseModel):
    """How :func:`quantize_model` quantizes (defaults: what the shipped int8 model used).

    Attributes:
        quant_format: "QDQ" (standard ONNX operators, default) or "QOperator" (onnxruntime-only).
        per_channel: one weight scale per output channel (accuracy; cost is negligible here).
        reduce_range: 7-bit weights, for x86 CPUs without VNNI where 8-bit products can saturate.
        max_intermediate_outputs: calibration folds its min/max every this many images, bounding
            memory (each image's activations are ~10 MB at 256x512).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    quant_format: Literal["QDQ", "QOperator"] = "QDQ"
    per_channel: bool = True
    reduce_range: bool = False
    max_intermediate_outputs: int = Field(default=8, ge=1)


@dataclass(frozen=True)
class QuantizeResult:
    """What :func:`quantize_model` wrote.

    Attributes:
        out_path: the int8 ONNX file.
        n_images: number of calibration images used.
        calibration_data: the ``calibration_data`` metadata written (image sources and counts).
        contract: the output model's contract as :meth:`DepthModel.load` reads it.
    """

    out_path: Path
    n_images: int
    calibration_data: str
    contract: ModelContract


def describe_calibration(images: Iterable[CalibImage]) -> str:
    """One line naming the calibration images: count, then ``folder (n)`` per folder of files."""
    folders: Counter[str] = Counter()
    arrays = 0
    for image in images:
        if isinstance(image, np.ndarray):
            arrays += 1
        else:
            folders[str(Path(image).resolve().parent)] += 1
    parts = [f"{folder} ({n})" for folder, n in folders.items()]
    if arrays:
        parts.append(f"{arrays} in-memory arrays")
    total = sum(folders.values()) + arrays
    return f"{total} images: " + "; ".join(parts)


def _images_in(folder: Path) -> list[Path]:
    """A KITTI-layout sequence folder's ``image_0/`` images, else the folder's own images."""
    if (folder / "image_0").is_dir():
        folder = folder / "image_0"
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def find_images(sources: Iterable[str | Path], stride: int = 1, max_images: int | None = None) -> list[Path]:
    """Image files named by folders or glob patterns, thinned (for calibration or a check).

    Args:
        sources: each a KITTI-layout sequence folder (its ``image_0/*``), a folder of images, an
            image file, or a glob pattern of any of these (e.g. ``runs/synth_train/w20*/image_0/000000.png``).
        stride: keep every ``stride``-th image of each folder (consecutive frames are near-duplicates).
        max_images: keep at most this many, evenly spaced over the whole list.

    Returns:
        Image paths in source order, sorted within each source.

    Raises:
        DatasetError: a source does not exist or holds no image (says which one).
    """
    if stride < 1 or (max_images is not None and max_images < 1):
        raise DatasetError(f"stride ({stride}) and max_images ({max_images}) must be at least 1")
    found: list[Path] = []
    for source in sources:
        text = str(source)
        matches = [Path(m) for m in sorted(glob.glob(text))] if any(c in text for c in "*?[") else [Path(text)]
        images: list[Path] = []
        for match in matches:
            if match.is_dir():
                images += _images_in(match)
            elif match.is_file() and match.suffix.lower() in IMAGE_SUFFIXES:
                images.append(match)
        if not images:
            raise DatasetError("image source holds no image: give a KITTI sequence folder (with "
                               "image_0/), a folder of PNG/JPEG images, an image file, or a glob of them", text)
        found += images
    by_folder: dict[Path, list[Path]] = {}
    for path in found:
        by_folder.setdefault(path.parent, []).append(path)
    kept = [p for paths in by_folder.values() for p in paths[::stride]]
    if max_images is not None and len(kept) > max_images:
        picks = np.unique(np.linspace(0, len(kept) - 1, max_images).round().astype(int))
        kept = [kept[i] for i in picks]
    return kept


@dataclass(frozen=True)
class Agreement:
    """How far a candidate model's output is from a reference's: ``|log(d_cand / d_ref)|`` over
    every output cell of every image (0.01 ≈ 1 % relative difference in depth).

    Attributes:
        n_images: images compared.
        median / p95 / max: statistics of the absolute log ratio (dimensionless).
    """

    n_images: int
    median: float
    p95: float
    max: float


def compare_models(reference: DepthModel, candidate: DepthModel, images: Iterable[CalibImage]) -> Agreement:
    """Per-cell agreement of two models' ``d_frac`` on the same images (files or uint8 arrays).

    Raises:
        DepthModelError: no image given, or an output is not positive (log undefined).
    """
    ratios: list[np.ndarray] = []
    for image in images:
        pixels = _pixels(image)
        ref = reference.predict_d_frac([pixels], _spanning_cameras(reference, pixels))[0].astype(np.float64)
        cand = candidate.predict_d_frac([pixels], _spanning_cameras(candidate, pixels))[0].astype(np.float64)
        if np.any(ref <= 0) or np.any(cand <= 0):
            raise DepthModelError("a model output a non-positive disparity: cannot compare in log space")
        ratios.append(np.abs(np.log(cand / ref)).ravel())
    if not ratios:
        raise DepthModelError("compare_models needs at least one image")
    all_ratios = np.concatenate(ratios)
    return Agreement(n_images=len(ratios), median=float(np.median(all_ratios)),
                     p95=float(np.percentile(all_ratios, 95)), max=float(all_ratios.max()))


def _pixels(image: CalibImage) -> np.ndarray:
    """A calibration/check image as pixels: arrays as given, files read as gray."""
    return image if isinstance(image, np.ndarray) else load_image(Path(image), color=False)


def _spanning_cameras(model: DepthModel, pixels: np.ndarray) -> list[PinholeCamera] | None:
    """For a contract-v2 model: the camera whose canonical warp maps ``pixels`` exactly onto the
    whole network input (the v1 resize), so calibration and agreement checks need no intrinsics:
    they only need inputs distributed like real ones. None for v1 models."""
    if not model.contract.uses_canonical_camera:
        return None
    canonical = model.contract.canonical_camera()
    h, w = pixels.shape[:2]
    sx, sy = canonical.width_px / w, canonical.height_px / h
    return [PinholeCamera(fx_px=canonical.fx_px / sx, fy_px=canonical.fy_px / sy, cx_px=(w - 1) / 2,
                          cy_px=(h - 1) / 2, width_px=w, height_px=h)]


def _drop_unused_opsets(model) -> None:
    """Remove opset imports no node uses (onnxruntime's pre-processing registers all of its
    contrib domains), so a runtime without them still loads the standard-operator QDQ graph."""
    used = {node.domain for node in model.graph.node} | {""}
    keep = [op for op in model.opset_import if op.domain in used or op.domain == "ai.onnx"]
    del model.opset_import[:]
    model.opset_import.extend(keep)


class _CalibrationReader:
    """onnxruntime ``CalibrationDataReader`` protocol over images, preprocessed by the model."""

    def __init__(self, model: DepthModel, images: Iterable[CalibImage]) -> None:
        self._model = model
        self._images: Iterator[CalibImage] = iter(images)
        self.count = 0

    def get_next(self) -> dict[str, np.ndarray] | None:
        image = next(self._images, None)
        if image is None:
            return None
        self.count += 1
        pixels = _pixels(image)
        return {self._model.contract.input_name: self._model.preprocess([pixels], _spanning_cameras(self._model, pixels))}


def quantize_model(src_onnx: str | Path, out_onnx: str | Path, calib_images: Iterable[CalibImage],
                   config: QuantizeConfig | None = None, calibration_data: str | None = None,
                   ) -> QuantizeResult:
    """Write a static int8 copy of the float32 depth model ``src_onnx`` to ``out_onnx``.

    Args:
        src_onnx: a float32 metricslam depth model (its contract is checked on load).
        out_onnx: output file; written only when quantization succeeded.
        calib_images: image files (any format OpenCV reads, gray or colour) or uint8 arrays
            ((H, W) gray or (H, W, 3) RGB, any size) from the model's training data. Iterated once.
        config: quantizer settings; ``None`` for the defaults.
        calibration_data: text for the ``calibration_data`` metadata key; default
            :func:`describe_calibration` of the images.

    Raises:
        DepthModelError: the source is not a float32 metricslam model, no calibration image was
            given, ``onnx`` is missing, or onnxruntime failed to quantize or load the result.
        DatasetError / ImageError: a calibration image cannot be read or has a bad shape.
    """
    try:
        import onnx
        import onnxruntime
        from onnxruntime.quantization import (
            CalibrationMethod,
            QuantFormat,
            QuantType,
            quantize_static,
        )
        from onnxruntime.quantization.shape_inference import quant_pre_process
    except ImportError as exc:
        raise DepthModelError(f"quantization needs the onnx package ({exc}): "
                              "pip install 'metricslam[quantize]'") from exc

    config = config if config is not None else QuantizeConfig()
    src_path, out_path = Path(src_onnx), Path(out_onnx)
    source = DepthModel.load(src_path, threads=1)
    if source.contract.weights_precision != FLOAT32:
        raise DepthModelError(f"{src_path} is already {source.contract.weights_precision}: "
                              "quantize the float32 model it was made from (for the shipped int8 default: "
                              "metricslam.depth.FLOAT32_MODEL_PATH, models/depth_l3.onnx)")
    images = list(calib_images)
    if not images:
        raise DepthModelError("quantization needs at least one calibration image: pass training images")
    description = calibration_data if calibration_data is not None else describe_calibration(images)
    reader = _CalibrationReader(source, images)

    with tempfile.TemporaryDirectory(prefix="metricslam-quant-") as tmp:
        pre_path, q_path = Path(tmp) / "pre.onnx", Path(tmp) / "q.onnx"
        try:
            # Folds constants and fills value_info so every tensor gets calibrated. Symbolic shape
            # inference is skipped: plain ONNX shape inference is enough for this static graph.
            quant_pre_process(str(src_path), str(pre_path), skip_symbolic_shape=True)
            quantize_static(str(pre_path), str(q_path), reader,
                            quant_format=getattr(QuantFormat, config.quant_format),
                            per_channel=config.per_channel, reduce_range=config.reduce_range,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                            calibrate_method=CalibrationMethod.MinMax,
                            extra_options={"CalibMaxIntermediateOutputs": config.max_intermediate_outputs})
        except MetricSlamError:
            raise  # a calibration image could not be read: the message names it
        except Exception as exc:  # onnxruntime's quantizer raises untyped errors
            raise DepthModelError(f"onnxruntime could not quantize {src_path}: {exc}") from exc

        quantized = onnx.load(str(q_path))
        metadata = {p.key: p.value for p in onnx.load(str(src_path), load_external_data=False).metadata_props}
        settings = {"tool": f"onnxruntime {onnxruntime.__version__} quantize_static",
                    "activations": "uint8", "weights": "int8", "calibration": "MinMax",
                    **config.model_dump(exclude={"max_intermediate_outputs"})}
        metadata.update(weights_precision=INT8_STATIC, calibration_data=description,
                        quantization=json.dumps(settings))
        # onnxruntime 1.31 keeps the source's metadata_props and adds its own markers (onnx.infer,
        # onnx.quant.pre_process); writing the source's keys explicitly keeps the contract
        # independent of that behaviour, and leaves only metricslam's keys.
        onnx.helper.set_model_props(quantized, metadata)
        _drop_unused_opsets(quantized)
        staged = Path(tmp) / "out.onnx"
        onnx.save(quantized, str(staged))
        result_model = DepthModel.load(staged, threads=1)
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_bytes(staged.read_bytes())
    return QuantizeResult(out_path=out_path, n_images=reader.count, calibration_data=description,
                          contract=result_model.contract)
