"""Depth service settings: environment (``DEPTH_`` prefix) first, then command-line overrides.

Every field is printed at start-up (:meth:`DepthServiceSettings.log_summary`) so an operator can
see what a running instance was configured with. Example::

    DEPTH_PORT=8100 DEPTH_MAX_QUEUE=8 metricslam depth-service
"""

from __future__ import annotations

import logging
from pathlib import Path

from pydantic import Field, ValidationError, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from metricslam.errors import ConfigError, validation_problems
from metricslam.endpoints import DEFAULT_DEPTH_HOST, DEFAULT_DEPTH_PORT

log = logging.getLogger(__name__)

MIB = 1024 * 1024
#: multipart framing (boundaries, part headers) allowed on top of the images of a batch
BATCH_OVERHEAD_BYTES = 64 * 1024


class DepthServiceSettings(BaseSettings):
    """Operational settings of one depth-service process (not algorithm parameters).

    Admission control: at most ``max_concurrency`` requests run decode + inference at once; up
    to ``max_queue`` more wait for a slot, for at most ``request_timeout_s``. A request that
    finds the queue full gets 429, one that waits too long gets 503; both carry
    ``Retry-After: retry_after_s``.

    Abuse limits (connections, timeouts, body and decoded-image budgets) are the fields from
    ``max_connections`` on; docs/depth_service.md "Limits" says what each one refuses and how.
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
    threads: int = Field(1, ge=1, le=64, description="threads one request may use: onnxruntime "
                         "intra-op threads and OpenCV's pool (decode, resize)")
    max_concurrency: int = Field(
        2, ge=1, le=64, description="requests decoded and inferred at the same time (~ cores)"
    )
    max_queue: int = Field(32, ge=0, le=10_000, description="requests allowed to wait for a slot")
    request_timeout_s: float = Field(
        5.0, gt=0, le=600, description="longest wait for an inference slot before 503"
    )
    retry_after_s: int = Field(1, ge=0, le=3600, description="Retry-After on 429/503")
    max_body_bytes: int = Field(
        8 * MIB, ge=1024, description="largest encoded image: the /v1/disparity body, and each "
        "image part of a batch (enforced while streaming)"
    )
    max_batch: int = Field(8, ge=1, le=256, description="most images per batch request")
    batch_window_ms: float = Field(
        0.0, ge=0, le=100, description="micro-batching: a request waits this long for concurrent "
        "requests and runs the network once for all their images (metricslam_depth.batcher); "
        "0 = off (measured slower on 2 cores: docs/depth_service.md, bench/results/depth_service_batching_*.md)"
    )
    max_image_pixels: int = Field(
        4096 * 4096, ge=64, description="largest decoded image (width*height) accepted"
    )
    max_connections: int = Field(
        256, ge=8, le=65_536,
        description="open TCP connections held at once; a new one beyond this closes the longest-"
        "idle connection (no request running), or gets a plain 503 when every one is busy",
    )
    max_inflight_requests: int = Field(
        128, ge=1, le=65_536,
        description="requests being received or served at once (beyond: 503 + Retry-After); "
        "/healthz and /readyz are exempt so liveness probes keep answering",
    )
    header_timeout_s: float = Field(
        10.0, gt=0, le=600,
        description="a connection must deliver a complete request head (line + headers) within "
        "this long after it opens or starts a request, else it is closed",
    )
    keep_alive_timeout_s: float = Field(
        5.0, gt=0, le=600, description="an idle keep-alive connection is closed after this long"
    )
    body_timeout_s: float = Field(
        30.0, gt=0, le=3600, description="longest time to receive one request body (else 408)"
    )
    max_header_bytes: int = Field(
        32 * 1024, ge=1024, le=MIB, description="largest request line + headers (else 431, closed)"
    )
    max_buffered_body_bytes: int = Field(
        128 * MIB, ge=1024,
        description="upload bytes held in memory by all requests together (Content-Length, or the "
        "endpoint's limit when not declared, is reserved before reading); beyond it a request "
        "waits up to body_budget_wait_s, then 503",
    )
    body_budget_wait_s: float = Field(
        5.0, gt=0, le=600, description="longest wait for upload memory (max_buffered_body_bytes) "
        "before 503"
    )
    max_decoded_bytes: int = Field(
        32 * MIB, ge=1024,
        description="largest decoded image, width*height*channels*bytes-per-sample from the file "
        "header (checked before decoding; a 4096x4096 16-bit RGBA PNG is 128 MiB)",
    )
    log_level: str = Field("info", description="uvicorn / logging level")
    access_log: bool = Field(False, description="uvicorn access log (one line per request)")

    @property
    def max_batch_body_bytes(self) -> int:
        """Largest multipart body accepted by the batch endpoint (bytes)."""
        return self.max_body_bytes * self.max_batch + BATCH_OVERHEAD_BYTES

    @model_validator(mode="after")
    def _budget_fits_one_batch(self) -> "DepthServiceSettings":
        if self.max_buffered_body_bytes < self.max_batch_body_bytes:
            raise ValueError(
                f"max_buffered_body_bytes ({self.max_buffered_body_bytes}) must be at least one full "
                f"batch body, max_body_bytes*max_batch + {BATCH_OVERHEAD_BYTES} = "
                f"{self.max_batch_body_bytes}, or no maximal batch could ever be admitted"
            )
        return self

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
        raise ConfigError("invalid depth-service settings: "
                          + validation_problems(exc, env_prefix="DEPTH_", from_flags=given)) from exc
