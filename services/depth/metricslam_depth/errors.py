"""Problem-style (RFC 9457) error bodies: every 4xx/5xx says what went wrong and what to fix.

Body (``Content-Type: application/problem+json``)::

    {"type": "urn:metricslam:problem:undecodable-image", "code": "undecodable-image",
     "title": "Image could not be decoded", "status": 400,
     "detail": "... what to do about it ...", "instance": "/v1/disparity"}

Handlers here turn :class:`RequestProblem`, FastAPI's validation errors, Starlette's HTTP errors
and, as a last resort, any other exception into that shape, so no endpoint ever answers with an
HTML page or a bare traceback. Bodies never carry file paths or exception names/text (those are
logged); see :mod:`metricslam_depth.disclosure`.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from metricslam.errors import MetricSlamError

from .schemas import FX_MAX_PX, FX_MIN_PX, PROBLEM_MEDIA_TYPE, Problem

log = logging.getLogger(__name__)

_TITLES: dict[int, tuple[str, str]] = {
    400: ("bad-request", "Bad request"),
    404: ("not-found", "No such endpoint"),
    405: ("method-not-allowed", "Method not allowed"),
    406: ("not-acceptable", "Response type not available"),
    413: ("body-too-large", "Request body too large"),
    415: ("unsupported-media-type", "Unsupported media type"),
    422: ("invalid-parameter", "Invalid request parameter"),
    429: ("overloaded", "Too many requests queued"),
    500: ("internal", "Internal server error"),
    503: ("unavailable", "Service unavailable"),
}


class RequestProblem(MetricSlamError):
    """A request the depth service refuses; rendered as a problem body with ``status``.

    Args:
        status: HTTP status code (4xx or 5xx).
        code: short machine-readable slug, e.g. ``"undecodable-image"``.
        title: one-line summary (same for every instance of ``code``).
        detail: what was wrong with *this* request and how to fix it.
        headers: extra response headers (e.g. ``Retry-After``).
    """

    def __init__(
        self,
        status: int,
        code: str,
        title: str,
        detail: str,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(detail)
        self.status = status
        self.code = code
        self.title = title
        self.detail = detail
        self.headers = headers or {}


def problem_response(
    status: int,
    code: str,
    title: str,
    detail: str,
    instance: str,
    headers: dict[str, str] | None = None,
    errors: list[dict] | None = None,
) -> JSONResponse:
    """Build the ``application/problem+json`` response for one problem."""
    body = Problem(
        type=f"urn:metricslam:problem:{code}",
        code=code,
        title=title,
        status=status,
        detail=detail,
        instance=instance,
        errors=errors,
    )
    return JSONResponse(
        body.model_dump(exclude_none=True),
        status_code=status,
        headers=headers,
        media_type=PROBLEM_MEDIA_TYPE,
    )


def _validation_errors(exc: RequestValidationError) -> tuple[str, list[dict]]:
    items: list[dict] = []
    parts: list[str] = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err.get("loc", ()))
        msg = str(err.get("msg", "invalid"))
        items.append({"loc": loc, "msg": msg})
        parts.append(f"{loc}: {msg}")
    hint = (
        f" fx is the camera's focal length in pixels at the uploaded image's resolution: a finite "
        f"number with {FX_MIN_PX:g} <= fx <= {FX_MAX_PX:g} (e.g. ?fx=718.856 for KITTI 00-02)."
        if any("fx" in i["loc"] for i in items)
        else ""
    )
    if any(i["loc"].rsplit(".", 1)[-1] in ("fy", "cx", "cy") for i in items):
        hint += (
            " fy (optional, default fx) has fx's range; cx and cy (optional, default the image "
            "centre) are the principal point in pixels of the uploaded image: finite, "
            "0 <= cx <= width, 0 <= cy <= height."
        )
    return "; ".join(parts) + "." + hint, items


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers that give every error response the problem shape."""

    @app.exception_handler(RequestProblem)
    async def _problem(request: Request, exc: RequestProblem) -> JSONResponse:
        return problem_response(
            exc.status, exc.code, exc.title, exc.detail, request.url.path, exc.headers
        )

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        detail, items = _validation_errors(exc)
        return problem_response(
            422, "invalid-parameter", "Invalid request parameter", detail, request.url.path,
            errors=items,
        )

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        code, title = _TITLES.get(exc.status_code, ("http-error", "HTTP error"))
        detail = str(exc.detail)
        if exc.status_code == 404:
            detail = f"{request.url.path} does not exist; see /docs or /openapi.json for endpoints."
        elif exc.status_code == 405:
            detail = f"{request.method} is not allowed on {request.url.path}; see /openapi.json."
        return problem_response(
            exc.status_code, code, title, detail, request.url.path, dict(exc.headers or {})
        )

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        # the exception (type, text, traceback) goes to the log only, never to the caller
        log.exception("unexpected error on %s %s", request.method, request.url.path)
        return problem_response(
            500, "internal", "Internal server error",
            "the server failed unexpectedly; this is a bug in the depth service, please report it "
            "with the request that caused it and the time (the server log has the details).",
            request.url.path,
        )
