"""Settings of the SLAM service, from the environment (prefix ``SLAM_``) or the CLI.

Example: ``SLAM_ZENOH_ENDPOINT=tcp/router:7447 SLAM_DEPTH_URL=http://depth:8000 metricslam
slam-service``. Algorithm parameters are not here: they are the frozen ``VOConfig`` presets.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class SlamServiceSettings(BaseSettings):
    """Service-level settings (network, queues, depth client). Logged at start-up.

    Attributes:
        zenoh_endpoint: router endpoint to connect to, e.g. ``tcp/127.0.0.1:7447``.
        zenoh_mode: ``client`` (connect to a router) or ``peer``.
        depth_url: base URL of the depth service; None runs without learned scale.
        use_scale: add learned scale factors (False = the ``--no-scale`` baseline).
        preset: ``VOConfig`` preset name.
        session_kind: ``pipeline`` (the real SLAM core) or ``identity`` (transport only:
            identity poses, for transport benchmarks).
        queue_size: frames buffered per camera; when full the oldest is dropped and counted.
        status_period_s: how often ``…/status`` is published (and the depth service probed).
        depth_timeout_s / depth_connect_timeout_s / depth_retries / depth_backoff_s: HTTP client.
        keyframe_images: attach the keyframe image to ``…/keyframe`` messages.
        frame_key_expr: which cameras this worker serves, e.g. ``metricslam/fleet-a-$*/frame``
            (partition cameras across SLAM workers; docs/deployment.md).
        rerun: live view with rerun-sdk: ``web`` or a ``.rrd`` path (needs the ``viz`` extra).
    """

    model_config = SettingsConfigDict(env_prefix="SLAM_", frozen=True, extra="forbid")

    zenoh_endpoint: str = "tcp/127.0.0.1:7447"
    zenoh_mode: Literal["client", "peer"] = "client"
    depth_url: str | None = "http://127.0.0.1:8000"
    use_scale: bool = True
    preset: str = "kitti"
    session_kind: Literal["pipeline", "identity"] = "pipeline"
    queue_size: int = Field(default=8, ge=1, le=10_000)
    status_period_s: float = Field(default=1.0, gt=0)
    depth_timeout_s: float = Field(default=5.0, gt=0)
    depth_connect_timeout_s: float = Field(default=0.5, gt=0)
    depth_retries: int = Field(default=2, ge=0, le=10)
    depth_backoff_s: float = Field(default=0.2, ge=0)
    keyframe_images: bool = False
    frame_key_expr: str = "metricslam/*/frame"
    rerun: str | None = None



