"""The CPU work of one request, run on a worker thread: decode -> network -> metric -> encode.

Images are decoded straight to gray, large JPEGs at 1/2 or 1/4 size when that still holds
at least the network input's pixel density (:func:`~metricslam_depth.imaging.decode_gray`).

Contract version 1 resizes each whole image to the network input and uses only ``fx``; version
2 (canonical camera) warps each image with its full camera (``fx, fy, cx, cy``,
:mod:`metricslam_depth.intrinsics`) and maps the answer back onto the uploaded image's grid
(NaN — ``null`` in JSON — outside the canonical field of view). Either way ``d_frac`` is served
as a fraction of the uploaded width for the caller's ``fx``, so ``inv_depth_per_m = d_frac ·
image_width_px / (fx_px · baseline_m)`` holds for both.

An image with (almost) no texture — blank, black, a lens cap, a uniform wall — still gets the
network's output, but flagged ``valid: false`` with the reason (``X-Valid`` in the binary form):
the network answers something plausible-looking for any input, and no depth can be read from
an image without contrast (:func:`flat_image_reason`).

Everything blocking lives here so the event loop only moves bytes. The response body is
encoded on the worker too (JSON of 2x32x64 floats is not free), inside the admission slot.
"""

from __future__ import annotations

import io
import math
import time
from dataclasses import dataclass

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.depth import DepthModel
from metricslam.depth.validity import flat_image_reason
from metricslam.disparity import inv_depth_from_width_fraction
from metricslam.errors import ImageError

from .batcher import MicroBatcher
from .errors import RequestProblem
from .imaging import decode_gray, read_header
from .intrinsics import CameraQuery, decoded_camera
from .metrics import ServiceMetrics
from .schemas import BatchResponse, DisparityResponse, DisparityResult


@dataclass(frozen=True)
class Upload:
    """One encoded image as received: bytes and its normalised media type."""

    data: bytes | bytearray
    media_type: str


@dataclass(frozen=True)
class Prediction:
    """Network output for a list of uploads.

    Attributes:
        d_frac: (B, h, w) float32 disparity / uploaded image width, for ``fx_px``.
        inv_depth_per_m: (B, h, w) float32 metric inverse depth, 1/m, for the caller's camera
            (NaN outside a version-2 model's field of view).
        sizes_px: (width, height) of each uploaded image.
        fx_px / fy_px: the caller's focal lengths (pixels, at the uploaded resolution).
        principal_points_px: (cx, cy) used for each image (pixels of the uploaded image).
        inference_ms: network time (milliseconds) for the whole list.
        invalid_reasons: per image, None when its map can be used, else why not
            (:func:`flat_image_reason`).
    """

    d_frac: np.ndarray
    inv_depth_per_m: np.ndarray
    sizes_px: list[tuple[int, int]]
    fx_px: float
    fy_px: float
    principal_points_px: list[tuple[float, float]]
    inference_ms: float
    invalid_reasons: tuple[str | None, ...] = ()

    def valid(self, i: int) -> bool:
        return i >= len(self.invalid_reasons) or self.invalid_reasons[i] is None


class DepthPipeline:
    """Turns uploads into :class:`Prediction` and renders them as JSON or ``.npy`` bytes.

    Args:
        model: the loaded network.
        max_pixels: largest accepted decoded image, width*height.
        max_decoded_bytes: largest decoded raster, width*height*channels*bytes-per-sample.
        metrics: where decode / inference times go.
    """

    def __init__(
        self, model: DepthModel, max_pixels: int, max_decoded_bytes: int, metrics: ServiceMetrics,
        batch_window_s: float = 0.0, max_batch_images: int = 8,
    ) -> None:
        self.model = model
        self.max_pixels = max_pixels
        self.max_decoded_bytes = max_decoded_bytes
        self.metrics = metrics
        # the network call: shared between concurrent requests with a batch window
        # (``DEPTH_BATCH_WINDOW_MS``), else the model's own
        self._network = (MicroBatcher(model.predict_d_frac, batch_window_s, max_batch_images).predict
                         if batch_window_s > 0 else model.predict_d_frac)

    def _min_decode_size(self, upload: Upload, query: CameraQuery) -> tuple[int, int]:
        """(width, height) the decoded image must keep (the JPEG reduction may not go below)."""
        c = self.model.contract
        if not c.uses_canonical_camera:
            return c.input_width, c.input_height  # the whole image is resized to the input
        header = read_header(upload.data, upload.media_type)
        scale = max(c.canonical_fx_px / query.fx_px, c.canonical_fy_px / query.fy_or_fx)
        return math.ceil(header.width_px * scale), math.ceil(header.height_px * scale)

    def predict(self, uploads: list[Upload], fx_px: float, route: str, fy_px: float | None = None,
                cx_px: float | None = None, cy_px: float | None = None) -> Prediction:
        """Decode every upload and run the network once on the whole list.

        The intrinsics are the request's (pixels of the uploaded images); absent ``fy_px``,
        ``cx_px``, ``cy_px`` default to ``fx_px`` and each image's centre
        (:class:`~metricslam_depth.intrinsics.CameraQuery`).

        Consumes the uploads: each encoded image held in a ``bytearray`` is emptied as soon as it
        is decoded, so a batch never holds the encoded and the decoded copy of every image at
        once (for a maximal batch that halves the peak memory of the request).

        Raises:
            RequestProblem: 400/413 for an image that cannot be used, 422 for a principal point
                off it (says which one).
        """
        query = CameraQuery(fx_px, fy_px, cx_px, cy_px)
        images, sizes, points, cameras, invalid = [], [], [], [], []
        c = self.model.contract
        for index, upload in enumerate(uploads):
            t0 = time.perf_counter()
            try:
                image, size_px = decode_gray(
                    upload.data, upload.media_type, self.max_pixels, self.max_decoded_bytes,
                    min_size_px=self._min_decode_size(upload, query),
                )
                if c.uses_canonical_camera:
                    camera = query.camera(*size_px)
                    cameras.append(decoded_camera(camera, (image.shape[1], image.shape[0])))
                    points.append((camera.cx_px, camera.cy_px))
                else:
                    points.append(query.principal_point(*size_px))
            except RequestProblem as exc:
                if len(uploads) > 1:
                    exc.detail = f"image {index}: {exc.detail}"
                raise
            images.append(image)
            invalid.append(flat_image_reason(image))
            sizes.append(size_px)  # as uploaded (the intrinsics refer to it), not as decoded
            if isinstance(upload.data, bytearray):
                upload.data.clear()
            self.metrics.decode.observe(time.perf_counter() - t0)
        t0 = time.perf_counter()
        try:
            d_frac = self._network(images, cameras or None)
        except ImageError as exc:  # our own message about the image (shape, dtype), no internals
            raise RequestProblem(400, "unusable-image", "Image not usable", str(exc)) from exc
        infer_s = time.perf_counter() - t0
        self.metrics.inference.labels(route).observe(infer_s)
        if c.uses_canonical_camera:
            d_frac, inv = self._from_canonical(d_frac, cameras, sizes, query.fx_px)
        else:
            baseline_m = c.baseline_m
            inv = np.empty_like(d_frac)
            for i, (width_px, _) in enumerate(sizes):
                inv[i] = inv_depth_from_width_fraction(d_frac[i], query.fx_px, float(width_px), baseline_m)
        return Prediction(d_frac, inv, sizes, float(query.fx_px), float(query.fy_or_fx), points,
                          infer_s * 1e3, tuple(invalid))

    def _from_canonical(self, d_frac: np.ndarray, cameras: list[PinholeCamera], sizes: list[tuple[int, int]],
                        fx_px: float) -> tuple[np.ndarray, np.ndarray]:
        """Version 2: network output (B, h, w) -> (d_frac per uploaded width, inverse depth) on the
        grid spanning each image (the decoded image spans the uploaded one)."""
        baseline_m = self.model.contract.baseline_m
        inv = np.empty_like(d_frac)
        caller = np.empty_like(d_frac)
        for i, camera in enumerate(cameras):
            inv[i] = self.model.inv_depth_map(d_frac[i], (camera.width_px, camera.height_px),
                                              camera=camera).inv_depth_per_m
            caller[i] = inv[i].astype(np.float64) * (fx_px * baseline_m / sizes[i][0])
        return caller, inv

    # ----- rendering (also on the worker thread) -----

    def _result(self, p: Prediction, i: int) -> DisparityResult:
        return DisparityResult.model_construct(
            image_width_px=p.sizes_px[i][0],
            image_height_px=p.sizes_px[i][1],
            cx_px=p.principal_points_px[i][0],
            cy_px=p.principal_points_px[i][1],
            shape=[int(p.d_frac.shape[1]), int(p.d_frac.shape[2])],
            d_frac=p.d_frac[i].tolist(),
            inv_depth_per_m=p.inv_depth_per_m[i].tolist(),
            valid=p.valid(i),
            invalid_reason=None if p.valid(i) else p.invalid_reasons[i],
        )

    def render_json(self, p: Prediction, batch: bool) -> bytes:
        """JSON body: :class:`DisparityResponse` (single) or :class:`BatchResponse` (batch)."""
        c = self.model.contract
        if not batch:
            one = self._result(p, 0)
            body = DisparityResponse.model_construct(
                **dict(one), model_id=c.model_id, fx_px=p.fx_px, fy_px=p.fy_px, baseline_m=c.baseline_m,
                inference_ms=p.inference_ms,
            )
        else:
            body = BatchResponse.model_construct(
                model_id=c.model_id, fx_px=p.fx_px, fy_px=p.fy_px, baseline_m=c.baseline_m,
                inference_ms=p.inference_ms, results=[self._result(p, i) for i in range(len(p.sizes_px))],
            )
        return body.model_dump_json().encode()

    def render_npy(self, p: Prediction, batch: bool) -> tuple[bytes, dict[str, str]]:
        """``.npy`` body — float32 (2,h,w) or (B,2,h,w) [d_frac, inv_depth_per_m] — and headers."""
        stack = np.stack([p.d_frac, p.inv_depth_per_m], axis=1).astype(np.float32, copy=False)
        if not batch:
            stack = stack[0]
        buffer = io.BytesIO()
        np.save(buffer, np.ascontiguousarray(stack), allow_pickle=False)
        c = self.model.contract
        headers = {
            "X-Model-Id": c.model_id,
            "X-Fx-Px": repr(p.fx_px),
            "X-Fy-Px": repr(p.fy_px),
            "X-Cx-Px": ",".join(repr(cx) for cx, _ in p.principal_points_px),
            "X-Cy-Px": ",".join(repr(cy) for _, cy in p.principal_points_px),
            "X-Baseline-M": repr(c.baseline_m),
            "X-Image-Width-Px": ",".join(str(w) for w, _ in p.sizes_px),
            "X-Image-Height-Px": ",".join(str(h) for _, h in p.sizes_px),
            "X-Inference-Ms": f"{p.inference_ms:.3f}",
            "X-Valid": ",".join("1" if p.valid(i) else "0" for i in range(len(p.sizes_px))),
            "X-Array-Layout": ("(B,2,h,w)" if batch else "(2,h,w)") + " [d_frac, inv_depth_per_m]",
        }
        return buffer.getvalue(), headers
