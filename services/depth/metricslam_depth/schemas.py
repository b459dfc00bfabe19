"""Request/response models of the depth service (JSON bodies and the binary form's headers).

Arrays in JSON are row-major nested lists, ``[row][col]``, float32 values written exactly (a
JSON float parsed as float64 and cast to float32 gives the served value bit for bit).

Binary form (``Accept: application/x-npy``): the body is one NumPy ``.npy`` file holding a
float32 stack — ``(2, h, w)`` for one image, ``(B, 2, h, w)`` for a batch — with channel 0 =
``d_frac`` and channel 1 = ``inv_depth_per_m``; the scalar metadata travels in ``X-*`` headers
(:data:`BINARY_HEADERS`).

Cells outside a contract-version-2 model's field of view (the canonical camera, see
``docs/depth_model.md``) are NaN in ``.npy`` and ``null`` in JSON; version-1 models fill every cell.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from metricslam.depth.contract import PGM_MEDIA_TYPE

PROBLEM_MEDIA_TYPE = "application/problem+json"
NPY_MEDIA_TYPE = "application/x-npy"
IMAGE_MEDIA_TYPES = ("image/png", "image/jpeg", PGM_MEDIA_TYPE)

# Plausible focal length of the caller's camera, pixels at the uploaded image's resolution; the
# one place the service's fx bounds live. 1e5 px is a 0.6 degree field of view on a 1000 px wide
# image, already a telescope; larger values (and NaN/inf) are a units or parsing bug upstream.
FX_MIN_PX = 1e-3
FX_MAX_PX = 1e5
# The same bounds hold for fy. The principal point (cx, cy) must lie on the uploaded image,
# 0 <= cx <= width, 0 <= cy <= height (checked after decoding, see metricslam_depth.intrinsics).

#: header name -> meaning, for the binary (``application/x-npy``) form.
BINARY_HEADERS: dict[str, str] = {
    "X-Model-Id": "model_id of the network that produced the arrays",
    "X-Fx-Px": "the fx the caller passed (pixels, at the uploaded image's resolution)",
    "X-Fy-Px": "the fy used (the caller's, else fx)",
    "X-Cx-Px": "the cx used for each image (the caller's, else (width-1)/2), comma-separated for a batch",
    "X-Cy-Px": "the cy used for each image (the caller's, else (height-1)/2), comma-separated for a batch",
    "X-Baseline-M": "training baseline of the virtual stereo rig (metres)",
    "X-Image-Width-Px": "width of each uploaded image, comma-separated for a batch",
    "X-Image-Height-Px": "height of each uploaded image, comma-separated for a batch",
    "X-Inference-Ms": "network time for the whole request (milliseconds)",
    "X-Valid": "1 if the image's map can be used, 0 if not (a flat image: no contrast to read depth "
               "from; the JSON form says why), comma-separated for a batch",
    "X-Array-Layout": "'(2,h,w) [d_frac, inv_depth_per_m]' or '(B,2,h,w) [d_frac, inv_depth_per_m]'",
}


class _Out(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class Problem(_Out):
    """RFC 9457 problem body of every error response."""

    type: str = Field(description="URI naming the problem kind, urn:metricslam:problem:<code>")
    code: str = Field(description="short machine-readable problem kind, e.g. undecodable-image")
    title: str = Field(description="one-line summary of the problem kind")
    status: int = Field(ge=400, le=599, description="HTTP status code")
    detail: str = Field(description="what was wrong with this request and how to fix it")
    instance: str = Field(description="request path")
    errors: list[dict[str, Any]] | None = Field(
        None, description="per-parameter validation errors (422 only)"
    )


class DisparityResult(_Out):
    """Network output for one image and its metric inverse depth for the caller's camera."""

    image_width_px: int = Field(description="width of the uploaded image (pixels)")
    image_height_px: int = Field(description="height of the uploaded image (pixels)")
    cx_px: float = Field(description="principal point column used (the caller's cx, else (width-1)/2)")
    cy_px: float = Field(description="principal point row used (the caller's cy, else (height-1)/2)")
    shape: list[int] = Field(
        min_length=2, max_length=2, description="[h, w] of both arrays (coarse L3 output)"
    )
    d_frac: list[list[float | None]] = Field(
        description="disparity as a fraction of the uploaded image's width for fx_px and the "
        "training baseline, [row][col], shape (h, w); null outside the field of view of a "
        "canonical-camera (contract version 2) model"
    )
    inv_depth_per_m: list[list[float | None]] = Field(
        description="metric inverse depth 1/m = d_frac*image_width_px/(fx_px*baseline_m); "
        "0 where d_frac <= 0; null where d_frac is null"
    )
    valid: bool = Field(
        True, description="false when no depth can be read from the image (flat: blank, covered, "
        "uniform; see invalid_reason): the arrays are the network's output all the same, but "
        "they are NOT a measurement — do not use them"
    )
    invalid_reason: str | None = Field(None, description="why valid is false; null when valid")


class DisparityResponse(DisparityResult):
    """Answer of ``POST /v1/disparity`` (JSON form)."""

    model_id: str = Field(description="identifier of the network (see GET /v1/model)")
    fx_px: float = Field(description="the fx the caller passed (pixels)")
    fy_px: float = Field(description="the fy used (the caller's, else fx; pixels)")
    baseline_m: float = Field(description="training baseline of the virtual stereo rig (m)")
    inference_ms: float = Field(description="network time for this request (milliseconds)")


class BatchResponse(_Out):
    """Answer of ``POST /v1/disparity/batch`` (JSON form); results in upload order."""

    model_id: str
    fx_px: float
    fy_px: float = Field(description="the fy used (the caller's, else fx; pixels)")
    baseline_m: float
    inference_ms: float = Field(description="network time for the whole batch (milliseconds)")
    results: list[DisparityResult]


class Health(_Out):
    """``/healthz``: the process is up (says nothing about the model)."""

    status: str = Field("ok", description="always 'ok' while the process answers")


class Ready(_Out):
    """``/readyz``: 200 only once the model is loaded."""

    ready: bool
    model_id: str | None = None
    weights_precision: str | None = Field(
        None, description="'int8-static' (the shipped default) or 'float32'; the same network either way"
    )
    detail: str | None = None
