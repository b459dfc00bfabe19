"""Depth service settings: environment (``DEPTH_`` prefix) first, then command-line overrides.

Every field is printed at start-up (:meth:`DepthServiceSettings.log_summary`) so an operator can
see what a running instance was configured with. Example::

    DEPTH_PORT=8100 DEPTH_MAX_QUEUE=8 metricslam depth-service
"""

from __future__ import annotations

import logging
from pathlib import Path

from pydantic import Field, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict

from metricslam.errors import ConfigError
from metricslam.endpoints import DEFAULT_DEPTH_HOST, DEFAULT_DEPTH_PORT

log = logging.getLogger(__name__)

MIB = 1024 * 1024


class DepthServiceSettings(BaseSettings):
    """Operational settings of one depth-service process (not algorithm parameters).

    Admission control: at most ``max_concurrency`` requests run decode + inference at once; up
    to ``max_queue`` more wait for a slot, for at most ``request_timeout_s``. A request that
    finds the queue full gets 429, one that waits too long gets 503; both carry
    ``Retry-After: retry_after_s``.
    """

    model_config = SettingsConfigDict(env_prefix="DEPTH_", frozen=True, extra="forbid")

    host: str = Field(DEFAULT_DEPTH_HOST, description="interface to bind (0.0.0.0 for all)")
    port: int = Field(DEFAULT_DEPTH_PORT, ge=0, le=65535,
                      description="TCP port (0 = any free port); the SLAM service's default "
                      "depth_url points here")
    model_path: Path | None = Field(
        None, description="ONNX model file; None = the int8 model shipped inside metricslam "
        "(metricslam.depth.DEFAULT_MODEL_PATH; the float32 one is FLOAT32_MODEL_PATH)"
    )
    # Measured on the 2-core dev machine: two single-threaded requests in parallel beat one
    # two-threaded request (decode/resize/encode do not parallelise inside one request).
    threads: int = Field(1, ge=1, le=64, description="onnxruntime intra-op threads per request")
    max_concurrency: int = Field(
        2, ge=1, le=64, description="requests decoded and inferred at the same time (~ cores)"
    )
    max_queue: int = Field(32, ge=0, le=10_000, description="requests allowed to wait for a slot")
    request_timeout_s: float = Field(
        5.0, gt=0, le=600, description="longest wait for an inference slot before 503"
    )
    retry_after_s: int = Field(1, ge=0, le=3600, description="Retry-After on 429/503")
    max_body_bytes: int = Field(
        8 * MIB, ge=1024, description="largest encoded image accepted by /v1/disparity"
    )
    max_batch: int = Field(8, ge=1, le=256, description="most images per batch request")
    max_image_pixels: int = Field(
        4096 * 4096, ge=64, description="largest decoded image (width*height) accepted"
    )
    max_connections: int = Field(
        256, ge=1, description="open connections uvicorn serves at once (beyond: plain 503)"
    )
    log_level: str = Field("info", description="uvicorn / logging level")
    access_log: bool = Field(False, description="uvicorn access log (one line per request)")

    @property
    def max_batch_body_bytes(self) -> int:
        """Largest multipart body accepted by the batch endpoint (bytes)."""
        return self.max_body_bytes * self.max_batch + 64 * 1024

    def log_summary(self) -> None:
        """Log every setting on one line each (called at start-up)."""
        for name, value in self.model_dump().items():
            log.info("depth-service setting %s = %s", name, value)


def load_settings(**overrides: object) -> DepthServiceSettings:
    """Settings from the environment with ``overrides`` (e.g. CLI flags; ``None`` = unset).

    Raises:
        ConfigError: a value is invalid; the message names the field and the env variable.
    """
    given = {k: v for k, v in overrides.items() if v is not None}
    try:
        return DepthServiceSettings(**given)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc'])} (env DEPTH_{str(e['loc'][0]).upper()}): {e['msg']}"
            for e in exc.errors()
        )
        raise ConfigError(f"invalid depth-service settings: {problems}") from exc
