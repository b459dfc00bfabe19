"""Prometheus metrics of one depth-service app (own registry, so several apps can coexist).

Names (all prefixed ``depth_``):

* ``depth_requests_total{route, method, status}`` — every HTTP request answered;
* ``depth_request_latency_seconds{route}`` — wall time from request start to response end;
* ``depth_inference_seconds{route}`` — network time only (``predict_d_frac``);
* ``depth_decode_seconds`` — PNG/JPEG decode time per image;
* ``depth_queue_depth`` — requests waiting for an inference slot right now;
* ``depth_inflight`` — requests decoding/inferring right now;
* ``depth_rejected_total{reason}`` — requests refused by admission control
  (``queue_full`` -> 429, ``queue_timeout`` -> 503, ``not_ready`` -> 503, ``busy`` -> 503 over
  ``max_inflight_requests``, ``body_budget`` -> 503 no upload memory free in time);
* ``depth_body_bytes_reserved`` — upload bytes reserved by requests right now (of
  ``max_buffered_body_bytes``);
* ``depth_model_loaded`` — 1 once the model is loaded.
"""

from __future__ import annotations

import time

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)
from starlette.types import ASGIApp, Message, Receive, Scope, Send

_LATENCY_BUCKETS_S = (0.002, 0.005, 0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.2, 0.5, 1, 2, 5, 10)
_INFER_BUCKETS_S = (0.001, 0.002, 0.004, 0.008, 0.016, 0.032, 0.064, 0.128, 0.256, 1.0)


class ServiceMetrics:
    """The collectors of one app, registered in their own :class:`CollectorRegistry`."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.requests = Counter(
            "depth_requests", "HTTP requests answered", ["route", "method", "status"], registry=r
        )
        self.latency = Histogram(
            "depth_request_latency_seconds", "request wall time", ["route"],
            buckets=_LATENCY_BUCKETS_S, registry=r,
        )
        self.inference = Histogram(
            "depth_inference_seconds", "network time per request", ["route"],
            buckets=_INFER_BUCKETS_S, registry=r,
        )
        self.decode = Histogram(
            "depth_decode_seconds", "image decode time per image",
            buckets=_INFER_BUCKETS_S, registry=r,
        )
        self.queue_depth = Gauge(
            "depth_queue_depth", "requests waiting for an inference slot", registry=r
        )
        self.inflight = Gauge("depth_inflight", "requests decoding/inferring now", registry=r)
        self.rejected = Counter(
            "depth_rejected", "requests refused by admission control", ["reason"], registry=r
        )
        self.body_bytes_reserved = Gauge(
            "depth_body_bytes_reserved", "upload bytes reserved by requests now", registry=r
        )
        self.model_loaded = Gauge("depth_model_loaded", "1 once the model is loaded", registry=r)

    def exposition(self) -> tuple[bytes, str]:
        """(body, content type) of the Prometheus text exposition."""
        return generate_latest(self.registry), CONTENT_TYPE_LATEST


class MetricsMiddleware:
    """Pure ASGI middleware counting requests and timing them by route template.

    Routes are labelled by their template (``/v1/disparity``), unknown paths as ``other``, so
    a scanner cannot blow up label cardinality.
    """

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics, known_paths: frozenset[str]) -> None:
        self.app = app
        self.metrics = metrics
        self.known_paths = known_paths

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope.get("path", "")
        route = path if path in self.known_paths else "other"
        method = scope.get("method", "")
        method = method if method in {"GET", "POST", "HEAD", "OPTIONS", "PUT", "DELETE"} else "other"
        status = 500
        t0 = time.perf_counter()

        async def send_wrapper(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            self.metrics.latency.labels(route).observe(time.perf_counter() - t0)
            self.metrics.requests.labels(route, method, str(status)).inc()
