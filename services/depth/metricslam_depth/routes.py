"""HTTP endpoints of the depth service (OpenAPI documents every status each one can answer).

Order of checks on the inference endpoints, cheapest and most permanent first:
fx (422) -> Content-Type (415) -> declared body size (413) -> readiness (503) -> body read
with a hard limit (413) -> admission (429/503) -> decode (400/413) -> network.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse, Response
from starlette.requests import ClientDisconnect

from metricslam.depth import ModelContract

from .errors import RequestProblem
from .imaging import normalise_media_type
from .multipart import parse_batch
from .pipeline import DepthPipeline, Upload
from .schemas import (
    BINARY_HEADERS,
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
        ge=1e-3,
        le=1e7,
        allow_inf_nan=False,
        description="focal length fx of the camera in pixels, at the resolution of the uploaded "
        "image (e.g. 718.856 for KITTI 00-02); finite, 0.001 <= fx <= 1e7",
        examples=[718.856],
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
    413: _problem_doc("body, image or batch larger than the configured limits"),
    415: _problem_doc("Content-Type is not supported by this endpoint"),
    422: _problem_doc("fx missing, not a number, non-finite or out of range"),
    429: _problem_doc("too many requests waiting; retry after Retry-After", retry_after=True),
    503: _problem_doc("model not loaded yet, or no inference slot within the timeout", retry_after=True),
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
            "with its own Content-Type image/png or image/jpeg (a filename is optional); other "
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
            f"the depth model failed to load ({state.load_error}); fix the model path "
            "(DEPTH_MODEL_PATH / --model) and restart the service."
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


def _too_large(limit: int, what: str) -> RequestProblem:
    return RequestProblem(
        413, "body-too-large", "Request body too large",
        f"the {what} is larger than the limit of {limit} bytes; send a smaller (downscaled or "
        "JPEG) image, or raise DEPTH_MAX_BODY_BYTES on the server.",
    )


def _check_declared_length(request: Request, limit: int, what: str) -> None:
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise _too_large(limit, what)


async def _read_body(request: Request, limit: int, what: str) -> bytes:
    """The whole body, refusing (413) as soon as more than ``limit`` bytes arrive."""
    chunks: list[bytes] = []
    size = 0
    try:
        async for chunk in request.stream():
            size += len(chunk)
            if size > limit:
                raise _too_large(limit, what)
            chunks.append(chunk)
    except ClientDisconnect:
        raise RequestProblem(
            400, "incomplete-body", "Request body incomplete",
            f"the connection closed after {size} bytes of the {what}; send the whole body.",
        ) from None
    return b"".join(chunks)


def _wants_npy(request: Request) -> bool:
    return NPY_MEDIA_TYPE in request.headers.get("accept", "").lower()


async def _answer(request: Request, uploads: list[Upload], fx: float, route: str, batch: bool) -> Response:
    pipeline = _pipeline(request)
    gate = request.app.state.depth.gate
    binary = _wants_npy(request)

    def work() -> tuple[bytes, dict[str, str]]:
        prediction = pipeline.predict(uploads, fx, route)
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
        "Body: the encoded PNG or JPEG file with its Content-Type. Answer: the network's coarse "
        "L3 disparity (`d_frac`, fraction of image width) and `inv_depth_per_m` for a camera with "
        "focal length `fx` at the uploaded image's width. `Accept: application/x-npy` returns a "
        ".npy float32 (2,h,w) stack [d_frac, inv_depth_per_m] with the metadata in X-* headers."
    ),
    responses={200: _ok_doc("JSON by default; .npy with Accept: application/x-npy"), **_ERRORS},
    openapi_extra=_image_body_doc(),
    tags=["inference"],
)
async def disparity(request: Request, fx: FxQuery) -> Response:
    route = "/v1/disparity"
    media_type = normalise_media_type(request.headers.get("content-type"))
    limit = request.app.state.depth.settings.max_body_bytes
    _check_declared_length(request, limit, "image")
    _pipeline(request)
    data = await _read_body(request, limit, "image")
    return await _answer(request, [Upload(data, media_type)], fx, route, batch=False)


@router.post(
    "/v1/disparity/batch",
    response_model=BatchResponse,
    summary="Disparity and metric inverse depth for several images in one network run",
    description=(
        "Body: multipart/form-data, one part per image, every part named `images` with its own "
        "Content-Type (image/png or image/jpeg). One `fx` applies to every image. Results keep "
        "the upload order. `Accept: application/x-npy` returns a .npy float32 (B,2,h,w) stack."
    ),
    responses={200: _ok_doc("JSON by default; .npy with Accept: application/x-npy"), **_ERRORS},
    openapi_extra=_batch_body_doc(),
    tags=["inference"],
)
async def disparity_batch(request: Request, fx: FxQuery) -> Response:
    route = "/v1/disparity/batch"
    settings = request.app.state.depth.settings
    content_type = request.headers.get("content-type", "")
    if content_type.split(";", 1)[0].strip().lower() != "multipart/form-data":
        raise RequestProblem(
            415, "unsupported-media-type", "Unsupported media type",
            f"got {content_type or 'no Content-Type'}; send multipart/form-data with one part per "
            "image, each named 'images' (e.g. curl -F images=@a.png -F images=@b.png).",
        )
    limit = settings.max_batch_body_bytes
    _check_declared_length(request, limit, "batch body")
    _pipeline(request)
    body = await _read_body(request, limit, "batch body")
    uploads = parse_batch(content_type, body, settings.max_batch)
    return await _answer(request, uploads, fx, route, batch=True)


# ----- model, health, readiness, metrics -----

@router.get(
    "/v1/model",
    response_model=ModelContract,
    summary="The model's contract: input size, output meaning, baseline, params, training commit",
    responses={503: _ERRORS[503]},
    tags=["model"],
)
async def model_contract(request: Request) -> ModelContract:
    return _pipeline(request).model.contract


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
    detail = f"model failed to load: {state.load_error}" if state.load_error else "model is loading"
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
