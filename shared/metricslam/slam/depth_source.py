"""Where the global graph gets metric inverse depth for a keyframe image.

One protocol, two implementations: :class:`OnnxDepthSource` (in-process onnxruntime, offline
runs) here, and the HTTP client of the depth service in the SLAM service package (the core may
not import httpx). The back end calls sources from a worker thread, so a slow or failing
source delays scale factors, never tracking.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.errors import DepthSourceError, MetricSlamError


@runtime_checkable
class DepthSource(Protocol):
    """Metric inverse depth for a whole image."""

    def inv_depth_map(self, image: np.ndarray, camera: PinholeCamera) -> np.ndarray:
        """(h, w) float32 metric inverse depth (1/m) on a grid covering the whole ``image``
        (any resolution; sample it with :func:`metricslam.depth.sample.sample_map`).

        Args:
            image: (H, W) uint8 gray or (H, W, 3) uint8 RGB.
            camera: intrinsics of ``image`` (``fx_px`` converts disparity to inverse depth; a
                canonical-camera model warps the image with all of them).

        Returns NaN in cells the network did not see (outside a canonical-camera model's field
        of view); consumers drop non-finite samples.

        Raises:
            DepthSourceError: the source could not answer (the caller skips this keyframe).
        """
        ...


class OnnxDepthSource:
    """In-process depth from the shipped (or a given) ONNX model via ``DepthModel``.

    The model loads lazily on the first request so constructing a back end stays cheap.
    Thread-safe (one lock around the session).

    Args:
        model_path: ONNX file, None for the shipped model.
        threads: onnxruntime intra-op threads.
    """

    def __init__(self, model_path: str | Path | None = None, threads: int = 1) -> None:
        self.model_path = model_path
        self.threads = int(threads)
        self._model = None
        self._lock = threading.Lock()

    def load(self) -> "OnnxDepthSource":
        """Load the model now instead of on the first request, so a missing or broken file is a
        start-up error, not one warning per keyframe (``metricslam run``). Returns ``self``.

        Raises:
            DepthModelError: the file is missing, not a loadable ONNX model, or its metadata
                does not match the code.
        """
        with self._lock:
            self._load()
        return self

    def _load(self):
        from metricslam.depth.model import DepthModel

        if self._model is None:
            self._model = DepthModel.load(self.model_path, threads=self.threads)
        return self._model

    def inv_depth_map(self, image: np.ndarray, camera: PinholeCamera) -> np.ndarray:
        """Metric inverse depth (h, w) float32 in 1/m for ``image`` taken with ``camera``.

        Raises:
            DepthSourceError: the model failed, or the image is flat (no contrast: blank, dark,
                covered lens) so its map would be a confident-looking guess — the depth service
                flags the same images ``valid: false`` (:mod:`metricslam.depth.validity`).
        """
        from metricslam.depth.model import to_gray_u8
        from metricslam.depth.validity import flat_image_reason

        reason = flat_image_reason(to_gray_u8(image))
        if reason is not None:
            raise DepthSourceError(f"no learned scale from this keyframe: {reason}")
        with self._lock:
            try:
                model = self._load()
                out = model.predict_inv_depth(image, camera=camera)  # v1 uses fx only, v2 all of it
            except DepthSourceError:
                raise
            except MetricSlamError as exc:
                raise DepthSourceError(f"in-process depth model failed: {exc}") from exc
        return np.asarray(out.inv_depth_per_m, dtype=np.float32)
