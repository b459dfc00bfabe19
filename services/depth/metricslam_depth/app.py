"""``create_app(settings)``: the depth service as a FastAPI application.

Life cycle: the lifespan starts loading the model on a background thread and the server
answers at once — ``/healthz`` is 200 from the start, ``/readyz`` and the inference endpoints
answer 503 (``Retry-After``) until the model is loaded, then 200. A model that fails to load
keeps the service unready; ``/readyz`` says so, the server log says why (paths and exception
text stay in the log, see :mod:`metricslam_depth.disclosure`).

Endpoints are in :mod:`metricslam_depth.routes`; error shapes in :mod:`metricslam_depth.errors`.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass

import cv2
from fastapi import FastAPI

from metricslam.depth import DEFAULT_MODEL_PATH, DepthModel

from .admission import AdmissionGate, InflightLimit
from .bodies import BodyBudget
from .disclosure import MODEL_LOAD_FAILED
from .errors import install_error_handlers
from .metrics import MetricsMiddleware, ServiceMetrics
from .pipeline import DepthPipeline
from .routes import router
from .settings import DepthServiceSettings

log = logging.getLogger(__name__)

API_VERSION = "1.0.0"
#: liveness / readiness probes: never refused by the in-flight request limit
PROBE_PATHS = frozenset({"/healthz", "/readyz"})


@dataclass
class ServiceState:
    """Mutable state of one app, held in ``app.state.depth``.

    ``pipeline`` is set exactly once, by the loader thread, when the model is ready;
    ``load_error`` (the public sentence, never the exception) is set instead if loading failed.
    """

    settings: DepthServiceSettings
    metrics: ServiceMetrics
    gate: AdmissionGate | None = None
    budget: BodyBudget | None = None
    pipeline: DepthPipeline | None = None
    load_error: str | None = None


def _load_model(state: ServiceState) -> None:
    s = state.settings
    # the max_concurrency workers are the parallelism: OpenCV's own pool (decode, resize) would
    # only add threads competing for the same cores, like onnxruntime's intra-op pool would
    cv2.setNumThreads(s.threads)
    try:
        model = DepthModel.load(s.model_path, threads=s.threads)
    except Exception:  # noqa: BLE001 - any failure must leave the service unready, not dead
        log.exception("depth model %s failed to load", s.model_path or DEFAULT_MODEL_PATH)
        state.load_error = MODEL_LOAD_FAILED
        return
    c = model.contract
    log.info(
        "depth model %s (%s weights, %s) loaded: input %dx%d -> output %dx%d, baseline %.4f m, "
        "%d params, commit %s",
        c.model_id, c.weights_precision, s.model_path or DEFAULT_MODEL_PATH, c.input_width, c.input_height,
        c.output_width, c.output_height, c.baseline_m, c.params, c.training_commit,
    )
    state.pipeline = DepthPipeline(model, s.max_image_pixels, s.max_decoded_bytes, state.metrics,
                                   batch_window_s=s.batch_window_ms / 1e3, max_batch_images=s.max_batch)
    state.metrics.model_loaded.set(1)


def create_app(settings: DepthServiceSettings | None = None) -> FastAPI:
    """Build the app; nothing heavy happens until its lifespan starts.

    Args:
        settings: service settings; ``None`` reads them from the environment.
    """
    settings = settings or DepthServiceSettings()
    metrics = ServiceMetrics()
    state = ServiceState(settings=settings, metrics=metrics)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        settings.log_summary()
        state.gate = AdmissionGate(
            settings.max_concurrency, settings.max_queue, settings.request_timeout_s,
            settings.retry_after_s, metrics,
        )
        state.budget = BodyBudget(
            settings.max_buffered_body_bytes, settings.body_budget_wait_s, settings.retry_after_s, metrics
        )
        loader = threading.Thread(target=_load_model, args=(state,), name="depth-model-load", daemon=True)
        loader.start()
        try:
            yield
        finally:
            await asyncio.to_thread(loader.join)
            await asyncio.to_thread(state.gate.shutdown)

    app = FastAPI(
        title="metricslam depth service",
        version=API_VERSION,
        summary="Coarse (L3) disparity and metric inverse depth from one image, by a tiny CNN.",
        description=(
            "POST an encoded PNG/JPEG image with the camera's fx; get the network's disparity "
            "(fraction of image width) and the metric inverse depth for that camera. Errors are "
            "RFC 9457 problem bodies that say what to fix. See docs/depth_service.md."
        ),
        lifespan=lifespan,
    )
    app.state.depth = state
    install_error_handlers(app)
    app.include_router(router)
    known = frozenset(getattr(r, "path", "") for r in [*app.routes, *router.routes]) - {""}
    # outermost last: metrics see every answer, the in-flight 503s included
    app.add_middleware(
        InflightLimit, max_requests=settings.max_inflight_requests, exempt_paths=PROBE_PATHS,
        retry_after_s=settings.retry_after_s, metrics=metrics,
    )
    app.add_middleware(MetricsMiddleware, metrics=metrics, known_paths=known)
    return app
