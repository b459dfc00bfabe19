"""The shipped depth model in onnxruntime (no torch): image -> L3 disparity -> metric inverse depth.

Two copies of the same network ship as package data: :data:`DEFAULT_MODEL_PATH`
(``depth_l3_int8.onnx``, static int8, ~2x faster on CPU, the default everywhere a model is not
named) and :data:`FLOAT32_MODEL_PATH` (``depth_l3.onnx``, the float32 export it was quantized
from; see docs/depth_quantization.md). The default is trained on real streets only;
:data:`RENDERED_MODEL_PATH` is a model trained with rendered streets too, for the rendered worlds
of ``metricslam synth`` (the demo, tests of the stack on rendered worlds).

Example::

    >>> from metricslam.depth import DepthModel, FLOAT32_MODEL_PATH
    >>> model = DepthModel.load()                      # the shipped int8 depth_l3_int8.onnx
    >>> model.contract.weights_precision
    'int8-static'
    >>> inv = model.predict_inv_depth(image_u8, fx_px=718.9)
    >>> inv.inv_depth_per_m.shape                      # (32, 64) covering the whole image
    >>> fp32 = DepthModel.load(FLOAT32_MODEL_PATH)     # the float32 source, same model_id

A contract-version-2 model (canonical camera, :mod:`metricslam.depth.canonical`) needs the
whole camera, and its map is NaN outside the canonical field of view::

    >>> v2 = DepthModel.load("canonical.onnx")
    >>> inv = v2.predict_inv_depth(image_u8, camera=PinholeCamera(fx_px=718.9, fy_px=718.9,
    ...                            cx_px=607.2, cy_px=185.2, width_px=1226, height_px=370))
    >>> inv.valid.mean()                               # share of the grid the network saw
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from metricslam.camera import PinholeCamera, check_intrinsics
from metricslam.depth.canonical import (
    CanonicalWarp,
    canonical_warp,
    cells_valid,
    inv_depth_from_canonical,
    to_caller_grid,
    to_canonical,
    valid_input_mask,
)
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
#: for rendered worlds (``metricslam synth``): int8, trained on KITTI 01/03 and six rendered
#: streets (the default until session 18, ``pyramid-l3-kitti0103fix-synthexact-no06``). The
#: real-streets default reads rendered worlds' scale far worse (the demo's world with each:
#: ``bench/results/accuracy_rendered_default.md``, ``accuracy_rendered_model.md``).
RENDERED_MODEL_PATH = _MODELS_DIR / "depth_l3_rendered_int8.onnx"


@dataclass(frozen=True)
class InvDepthMap:
    """The network's output for one image, on the L3 grid covering the whole image.

    Attributes:
        d_frac: (h, w) float32 left disparity as a fraction of the image's width, for the
            caller's ``fx_px`` and the training baseline — so ``inv_depth_per_m = d_frac ·
            image_width_px / (fx_px · baseline_m)`` for either contract version. Version 1: the
            network output itself; version 2: derived from ``inv_depth_per_m``.
        inv_depth_per_m: (h, w) float32 metric inverse depth for the caller's camera, 1/m; NaN
            where ``valid`` is False.
        image_width_px / image_height_px: size of the image the map covers (sample it with
            :func:`metricslam.depth.sample.sample_map` and ``image_size=(W, H)``).
        valid: (h, w) bool, cells the network saw (version 2: inside the canonical field of
            view); all True for version 1. ``None`` at construction means all True.
    """

    d_frac: np.ndarray
    inv_depth_per_m: np.ndarray
    image_width_px: int
    image_height_px: int
    valid: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.valid is None:
            object.__setattr__(self, "valid", np.ones(np.shape(self.inv_depth_per_m), dtype=bool))

    def depth_m(self) -> np.ndarray:
        """(h, w) float32 depth in metres (``inf`` where the inverse depth is 0, NaN where invalid)."""
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

    def warp_for(self, camera: PinholeCamera) -> CanonicalWarp:
        """Version 2: the warp from ``camera``'s image to the network input."""
        return canonical_warp(camera, self.contract.canonical_camera())

    def _cameras(self, images: Sequence[np.ndarray], cameras: Sequence[PinholeCamera] | None
                 ) -> list[PinholeCamera]:
        if cameras is None or len(cameras) != len(images):
            raise DepthModelError(
                f"model {self.contract.model_id!r} (contract_version 2, canonical camera) needs one "
                f"PinholeCamera per image (got {'none' if cameras is None else len(cameras)} for "
                f"{len(images)} images): pass cameras=[...] / camera=... with fx, fy, cx, cy")
        return list(cameras)

    def preprocess(self, images: Sequence[np.ndarray],
                   cameras: Sequence[PinholeCamera] | None = None) -> np.ndarray:
        """uint8 images of any size -> (B, 1, H_in, W_in) float32 normalized network input.

        Version 1: each whole image resized to the input (``cameras`` ignored). Version 2: each
        image warped to the canonical camera with its ``cameras[i]`` (required; padding outside
        the image, :func:`metricslam.depth.canonical.to_canonical`).
        """
        c = self.contract
        norm = c.normalization
        cams = self._cameras(images, cameras) if c.uses_canonical_camera else None
        batch = np.empty((len(images), 1, c.input_height, c.input_width), dtype=np.float32)
        for i, image in enumerate(images):
            gray = to_gray_u8(image)
            if cams is None:
                resized = cv2.resize(gray, (c.input_width, c.input_height), interpolation=cv2.INTER_AREA)
            else:
                resized, _ = to_canonical(gray, self.warp_for(cams[i]))
            batch[i, 0] = (resized.astype(np.float32) * norm.scale - norm.mean) / norm.std
        return batch

    def run(self, batch: np.ndarray) -> np.ndarray:
        """(B, 1, H_in, W_in) network input -> (B, h, w) float32 network output ``d_frac``."""
        (out,) = self._session.run([self.contract.output_name], {self.contract.input_name: batch})
        return np.asarray(out, dtype=np.float32).reshape(len(batch), self.contract.output_height,
                                                          self.contract.output_width)

    def predict_d_frac(self, images: Sequence[np.ndarray],
                       cameras: Sequence[PinholeCamera] | None = None) -> np.ndarray:
        """(B, h, w) float32 network output for a list of uint8 images (gray or RGB).

        Version 1: disparity / image width on the grid covering each image. Version 2 (needs
        ``cameras``): disparity / input width at the canonical focal, on the network's own
        grid (convert with :meth:`inv_depth_map`).
        """
        if len(images) == 0:
            raise ImageError("predict_d_frac needs at least one image")
        return self.run(self.preprocess(images, cameras))

    def inv_depth_map(self, d_frac: np.ndarray, size_px: tuple[int, int], fx_px: float | None = None,
                      camera: PinholeCamera | None = None) -> InvDepthMap:
        """One image's network output (h, w) -> :class:`InvDepthMap` on the grid spanning the image.

        Args:
            d_frac: (h, w) from :meth:`predict_d_frac` / :meth:`run`.
            size_px: (W, H) of the image the grid spans (for version 2: ``camera``'s size).
            fx_px: version 1: focal length at width W (default ``camera.fx_px``).
            camera: version 2 (required): the image's camera, as given to :meth:`preprocess`.
        """
        c = self.contract
        width_px, height_px = int(size_px[0]), int(size_px[1])
        if not c.uses_canonical_camera:
            fx = camera.fx_px if fx_px is None and camera is not None else fx_px
            if fx is None:
                raise DepthModelError("predict_inv_depth needs fx_px (or camera): the focal length in pixels")
            inv = inv_depth_from_width_fraction(d_frac, float(fx), float(width_px), c.baseline_m)
            return InvDepthMap(d_frac=d_frac, inv_depth_per_m=inv.astype(np.float32),
                               image_width_px=width_px, image_height_px=height_px)
        (cam,) = self._cameras([d_frac], None if camera is None else [camera])  # one image, one camera
        if (cam.width_px, cam.height_px) != (width_px, height_px):
            raise DepthModelError(f"camera is for {cam.width_px}x{cam.height_px} images, the map for "
                                  f"{width_px}x{height_px}: pass the camera of this image")
        warp = self.warp_for(cam)
        valid_cells = cells_valid(valid_input_mask(warp), d_frac.shape, float(c.valid_min_fraction))
        inv_in = inv_depth_from_canonical(d_frac, warp.canonical, c.baseline_m)
        inv = to_caller_grid(inv_in, valid_cells, warp)
        caller_d_frac = (inv.astype(np.float64) * (cam.fx_px * c.baseline_m / width_px)).astype(np.float32)
        return InvDepthMap(d_frac=caller_d_frac, inv_depth_per_m=inv, image_width_px=width_px,
                           image_height_px=height_px, valid=np.isfinite(inv))

    def predict_inv_depth(self, image: np.ndarray, fx_px: float | None = None,
                          camera: PinholeCamera | None = None, *, fy_px: float | None = None,
                          cx_px: float | None = None, cy_px: float | None = None) -> InvDepthMap:
        """Metric inverse depth (1/m) on the L3 grid covering one image.

        Version 1 models need only the focal length: ``fx_px``, or ``camera.fx_px`` (the old
        path, unchanged). Version 2 models need the whole camera: ``camera``, or all of
        ``fx_px, fy_px, cx_px, cy_px``; the image is warped to the canonical camera, and cells
        outside its field of view are NaN. Intrinsics refer to the image as passed (its own
        size, pixel centres at integers), not to the network input.
        """
        gray = to_gray_u8(image)
        height_px, width_px = gray.shape
        if camera is None and None not in (fx_px, fy_px, cx_px, cy_px):
            values = {"fx_px": float(fx_px), "fy_px": float(fy_px), "cx_px": float(cx_px),
                      "cy_px": float(cy_px), "width_px": int(width_px), "height_px": int(height_px)}
            check_intrinsics(**values)  # CameraError naming the implausible value
            camera = PinholeCamera(**values)
        cams = [camera] if camera is not None else None
        d_frac = self.predict_d_frac([gray], cams if self.contract.uses_canonical_camera else None)[0]
        return self.inv_depth_map(d_frac, (width_px, height_px), fx_px=fx_px, camera=camera)
