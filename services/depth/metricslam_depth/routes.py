"""HTTP endpoints of the depth service (OpenAPI documents every status each one can answer).

Order of checks on the inference endpoints, cheapest and most permanent first:
fx, fy, cx >= 0, cy >= 0 (422) -> Content-Type (415) -> declared body size (413) -> readiness
(503) -> upload memory budget (503) -> body streamed with a hard limit and deadline (413/408; a
batch image part is judged as it arrives) -> image headers: pixels and decoded bytes (400/413) ->
admission (429/503) -> decode (400) -> principal point on the decoded, upright image (422) ->
network. Everything before admission costs microseconds of the event loop per request and holds
no inference slot. (In front of all of it:
:class:`~metricslam_depth.admission.InflightLimit` and the connection guards.)
"""

from __future__ import annotations

import contextlib
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse, Response

from metricslam.depth import ModelContract

from . import bodies
from .disclosure import MODEL_LOAD_FAILED, public_contract
from .errors import RequestProblem
from .imaging import check_header, normalise_media_type
from .intrinsics import CameraQuery
from .multipart import BatchParser, boundary_of
from .pipeline import DepthPipeline, Upload
from .schemas import (
    BINARY_HEADERS,
    FX_MAX_PX,
    FX_MIN_PX,
    IMAGE_MEDIA_TYPES,
    NPY_MEDIA_TYPE,
    PROBLEM_MEDIA_TYPE,
    BatchResponse,
    DisparityResponse,
    Health,
    Problem,
    Ready,
)

router = APIRouter()

FxQuery = Annotated[
    float,
    Query(
        ge=FX_MIN_PX,
        le=FX_MAX_PX,
        allow_inf_nan=False,
        description="focal length fx of the camera in pixels, at the resolution of the uploaded "
        f"image (e.g. 718.856 for KITTI 00-02); finite, {FX_MIN_PX:g} <= fx <= {FX_MAX_PX:g}",
        examples=[718.856],
    ),
]
FyQuery = Annotated[
    float | None,
    Query(
        ge=FX_MIN_PX,
        le=FX_MAX_PX,
        allow_inf_nan=False,
        description="focal length fy in pixels at the uploaded resolution; default fx. Same bounds "
        "as fx. Used by canonical-camera (contract version 2) models; version-1 models ignore it",
        examples=[718.856],
    ),
]
CxQuery = Annotated[
    float | None,
    Query(
        ge=0.0,
        allow_inf_nan=False,
        description="principal point column cx in pixels of the uploaded image (origin at the centre "
        "of the top-left pixel); 0 <= cx <= image width, checked once the image is decoded; default "
        "(width-1)/2. Used by contract version 2 models; version-1 models ignore it",
        examples=[607.193],
    ),
]
CyQuery = Annotated[
    float | None,
    Query(
        ge=0.0,
        allow_inf_nan=False,
        description="principal point row cy in pixels of the uploaded image; 0 <= cy <= image height, "
        "checked once the image is decoded; default (height-1)/2. Used by contract version 2 models; "
        "version-1 models ignore it",
        examples=[185.216],
    ),
]


def _problem_doc(description: str, retry_after: bool = False) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "description": description,
        "content": {PROBLEM_MEDIA_TYPE: {"schema": Problem.model_json_schema()}},
    }
    if retry_after:
        doc["headers"] = {
            "Retry-After": {"description": "seconds to wait before retrying", "schema": {"type": "string"}}
        }
    return doc


_BINARY_DOC = {
    "schema": {"type": "string", "format": "binary"},
}
_ERRORS: dict[int | str, dict[str, Any]] = {
    400: _problem_doc("the image is empty, truncated, corrupt or not of the declared type"),
    408: _problem_doc("the body did not arrive within body_timeout_s"),
    413: _problem_doc("body, image part, decoded image (pixels or bytes) or batch larger than the "
                      "configured limits"),
    406: _problem_doc("Accept admits neither application/json nor application/x-npy (e.g. text/html)"),
    415: _problem_doc("Content-Type is not supported by this endpoint"),
    422: _problem_doc("fx missing, not a number, non-finite or out of range; fy, cx or cy not a "
                      "number, non-finite or out of range (cx/cy: off the decoded image)"),
    429: _problem_doc("too many requests waiting; retry after Retry-After", retry_after=True),
    503: _problem_doc("model not loaded yet, too many requests or uploads in progress, or no inference "
                      "slot within the timeout", retry_after=True),
}
_OK_HEADERS = {name: {"description": text, "schema": {"type": "string"}} for name, text in BINARY_HEADERS.items()}


def _image_body_doc() -> dict[str, Any]:
    return {
        "requestBody": {
            "required": True,
            "description": "the encoded image file, unchanged",
            "content": {media: _BINARY_DOC for media in IMAGE_MEDIA_TYPES},
        }
    }


def _batch_body_doc() -> dict[str, Any]:
    return {
        "requestBody": {
            "required": True,
            "description": "multipart/form-data with one part per image, all named 'images', each "
            "with its own Content-Type image/png, image/jpeg or image/x-portable-graymap (a filename is optional); other "
            "parts are ignored",
            "content": {
                "multipart/form-data": {
                    "schema": {
                        "type": "object",
                        "required": ["images"],
                        "properties": {
                            "images": {"type": "array", "items": {"type": "string", "format": "binary"}}
                        },
                    },
                    "encoding": {"images": {"contentType": ", ".join(IMAGE_MEDIA_TYPES)}},
                }
            },
        }
    }


def _ok_doc(description: str) -> dict[str, Any]:
    return {
        "description": description,
        "content": {NPY_MEDIA_TYPE: _BINARY_DOC},
        "headers": _OK_HEADERS,
    }


# ----- helpers -----

def _not_ready(request: Request) -> RequestProblem:
    state = request.app.state.depth
    if state.load_error is not None:
        detail = (
            f"{MODEL_LOAD_FAILED}; the operator must fix the model (DEPTH_MODEL_PATH or --model) "
            "and restart the service."
        )
    else:
        detail = "the depth model is still loading; retry after the Retry-After delay (see /readyz)."
    state.metrics.rejected.labels("not_ready").inc()
    return RequestProblem(
        503, "not-ready", "Model not loaded", detail,
        headers={"Retry-After": str(state.settings.retry_after_s)},
    )


def _pipeline(request: Request) -> DepthPipeline:
    pipeline = request.app.state.depth.pipeline
    if pipeline is None:
        raise _not_ready(request)
    return pipeline


def _free(data: bytearray) -> None:
    with contextlib.suppress(BufferError):  # still exported to a decoder: GC frees it
        data.clear()


#: what an inference answer can be: JSON (the default) or .npy
ANSWER_MEDIA_TYPES = ("application/json", NPY_MEDIA_TYPE)


def _accepted_ranges(request: Request) -> list[str]:
    """The media ranges of the ``Accept`` header with a non-zero quality (lower case)."""
    ranges = []
    for item in request.headers.get("accept", "").lower().split(","):
        media, *params = (part.strip() for part in item.split(";"))
        if not media:
            continue
        q = next((v for k, _, v in (p.partition("=") for p in params) if k.strip() == "q"), "1")
        try:
            if float(q) <= 0:
                continue
        except ValueError:
            pass  # a malformed q counts as accepted, as most servers treat it
        ranges.append(media)
    return ranges


def _wants_npy(request: Request) -> bool:
    """The answer's form from ``Accept``: ``.npy`` when it names application/x-npy, else JSON.

    Raises:
        RequestProblem: 406 when ``Accept`` admits neither (e.g. ``text/html`` from a browser),
            before the body is read.
    """
    ranges = _accepted_ranges(request)
    if not request.headers.get("accept", "").strip():
        return False
    if NPY_MEDIA_TYPE in ranges:
        return True
    if any(r in ("*/*", "application/*", "application/json") for r in ranges):
        return False
    raise RequestProblem(
        406, "not-acceptable", "Response type not available",
        f"Accept: {request.headers.get('accept')!r} admits none of {', '.join(ANSWER_MEDIA_TYPES)}; "
        "this is an API, not a web page: send Accept: application/json (or */*, or application/x-npy)",
    )


async def _answer(request: Request, uploads: list[Upload], query: CameraQuery, route: str,
                  batch: bool) -> Response:
    pipeline = _pipeline(request)
    gate = request.app.state.depth.gate
    binary = _wants_npy(request)  # checked before the body too; cheap to ask again

    def work() -> tuple[bytes, dict[str, str]]:
        prediction = pipeline.predict(uploads, query.fx_px, route, query.fy_px, query.cx_px, query.cy_px)
        if binary:
            return pipeline.render_npy(prediction, batch)
        return pipeline.render_json(prediction, batch), {}

    body, headers = await gate.run(work)
    media = NPY_MEDIA_TYPE if binary else "application/json"
    return Response(content=body, media_type=media, headers=headers)


# ----- inference -----

@router.post(
    "/v1/disparity",
    response_model=DisparityResponse,
    summary="Disparity and metric inverse depth for one image",
    description=(
        "Body: the encoded PNG or JPEG file, or a binary (P5) PGM of gray pixels (the cheapest to "
        "decode), with its Content-Type. Answer: the network's coarse "
        "L3 disparity (`d_frac`, fraction of image width) and `inv_depth_per_m` for a camera with "
        "focal length `fx` at the uploaded image's width (and `fy`, `cx`, `cy` for a canonical-camera "
        "model, contract version 2: cells outside its field of view are null / NaN). `Accept: "
        "application/x-npy` returns a .npy float32 (2,h,w) stack [d_frac, inv_depth_per_m] with the "
        "metadata in X-* headers."
    ),
    responses={200: _ok_doc("JSON by default; .npy with Accept: application/x-npy"), **_ERRORS},
    openapi_extra=_image_body_doc(),
    tags=["inference"],
)
async def disparity(request: Request, fx: FxQuery, fy: FyQuery = None, cx: CxQuery = None,
                    cy: CyQuery = None) -> Response:
    route = "/v1/disparity"
    state = request.app.state.depth
    settings = state.settings
    _wants_npy(request)  # 406 before a byte of the body is read
    media_type = normalise_media_type(request.headers.get("content-type"))
    limit = settings.max_body_bytes
    declared = bodies.declared_length(request, limit, "image")
    _pipeline(request)
    async with state.budget.reserve(limit if declared is None else declared):
        data = bytearray()
        try:
            await bodies.receive(request, limit, "image", settings.body_timeout_s, data.extend)
            check_header(data, media_type, settings.max_image_pixels, settings.max_decoded_bytes)
            query = CameraQuery(fx, fy, cx, cy)
            return await _answer(request, [Upload(data, media_type)], query, route, batch=False)
        finally:
            _free(data)  # with the reservation: an error's traceback must not keep the body alive


@router.post(
    "/v1/disparity/batch",
    response_model=BatchResponse,
    summary="Disparity and metric inverse depth for several images in one network run",
    description=(
        "Body: multipart/form-data, one part per image, every part named `images` with its own "
        "Content-Type (image/png, image/jpeg or image/x-portable-graymap). One `fx` (and `fy`, `cx`, "
        "`cy`) applies to every image; absent cx/cy default to each image's centre. Results keep "
        "the upload order. `Accept: application/x-npy` returns a .npy float32 (B,2,h,w) stack."
    ),
    responses={200: _ok_doc("JSON by default; .npy with Accept: application/x-npy"), **_ERRORS},
    openapi_extra=_batch_body_doc(),
    tags=["inference"],
)
async def disparity_batch(request: Request, fx: FxQuery, fy: FyQuery = None, cx: CxQuery = None,
                          cy: CyQuery = None) -> Response:
    route = "/v1/disparity/batch"
    state = request.app.state.depth
    settings = state.settings
    _wants_npy(request)  # 406 before a byte of the body is read
    content_type = request.headers.get("content-type", "")
    if content_type.split(";", 1)[0].strip().lower() != "multipart/form-data":
        raise RequestProblem(
            415, "unsupported-media-type", "Unsupported media type",
            f"got {content_type or 'no Content-Type'}; send multipart/form-data with one part per "
            "image, each named 'images' (e.g. curl -F images=@a.png -F images=@b.png).",
        )
    boundary_of(content_type)
    limit = settings.max_batch_body_bytes
    declared = bodies.declared_length(request, limit, "batch body")
    _pipeline(request)
    async with state.budget.reserve(limit if declared is None else declared):
        parser = BatchParser(
            content_type, settings.max_batch, settings.max_body_bytes, settings.max_image_pixels,
            settings.max_decoded_bytes,
        )
        try:
            await bodies.receive(request, limit, "batch body", settings.body_timeout_s, parser.write)
            return await _answer(request, parser.finish(), CameraQuery(fx, fy, cx, cy), route, batch=True)
        finally:
            parser.discard()


# ----- model, health, readiness, metrics -----

@router.get(
    "/v1/model",
    response_model=ModelContract,
    summary="The model's contract: version, input size, output meaning, baseline, canonical focal "
    "lengths (version 2), params, training commit",
    responses={503: _ERRORS[503]},
    tags=["model"],
)
async def model_contract(request: Request) -> ModelContract:
    return public_contract(_pipeline(request).model.contract)


@router.get("/healthz", response_model=Health, summary="Liveness: the process answers", tags=["ops"])
async def healthz() -> Health:
    return Health()


@router.get(
    "/readyz",
    response_model=Ready,
    summary="Readiness: 200 once the model is loaded, 503 before (or if it failed to load)",
    responses={503: {"model": Ready, "description": "model not loaded (yet)"}},
    tags=["ops"],
)
async def readyz(request: Request) -> JSONResponse:
    state = request.app.state.depth
    if state.pipeline is not None:
        c = state.pipeline.model.contract
        return JSONResponse(Ready(ready=True, model_id=c.model_id, weights_precision=c.weights_precision).model_dump())
    detail = MODEL_LOAD_FAILED if state.load_error else "model is loading"
    return JSONResponse(
        Ready(ready=False, detail=detail).model_dump(),
        status_code=503,
        headers={"Retry-After": str(state.settings.retry_after_s)},
    )


@router.get(
    "/metrics",
    summary="Prometheus metrics (text exposition format)",
    response_class=Response,
    responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}, "description": "metrics"}},
    tags=["ops"],
)
async def metrics(request: Request) -> Response:
    body, content_type = request.app.state.depth.metrics.exposition()
    return Response(content=body, media_type=content_type)
