"""Run the depth service under uvicorn (used by ``metricslam depth-service`` and ``python -m``)."""

from __future__ import annotations

import logging

from metricslam.errors import ConfigError

from .settings import DepthServiceSettings

log = logging.getLogger(__name__)


def serve(settings: DepthServiceSettings) -> None:
    """Serve until interrupted (SIGINT/SIGTERM shut down gracefully).

    Raises:
        ConfigError: the model file given in the settings does not exist.
    """
    import uvicorn

    from .app import create_app

    if settings.model_path is not None and not settings.model_path.is_file():
        raise ConfigError(
            f"depth model {settings.model_path} does not exist: pass --model PATH (or "
            "DEPTH_MODEL_PATH) pointing at an ONNX file exported by metricslam, or leave it unset "
            "for the shipped int8 model"
        )
    config = uvicorn.Config(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        access_log=settings.access_log,
        limit_concurrency=settings.max_connections,
        timeout_graceful_shutdown=10,
    )
    log.info("depth service listening on http://%s:%d", settings.host, settings.port)
    uvicorn.Server(config).run()
