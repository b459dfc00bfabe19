"""Settings of the SLAM service, from the environment (prefix ``SLAM_``) or the CLI.

Example: ``SLAM_ZENOH_ENDPOINT=tcp/router:7447 SLAM_DEPTH_URL=http://depth:8100 metricslam
slam-service``. Only the service's own plumbing is here (network, depth client, status, viewer).
What the SLAM sessions do — VO preset, graph, loops, learned scale on/off, queue sizes — is the
:class:`~metricslam.slam.system_config.SystemConfig` that offline runs use too (``--config
FILE.yaml`` / ``METRICSLAM_CONFIG``, ``METRICSLAM_*`` variables; :mod:`metricslam.slam.config_file`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict

from metricslam.endpoints import DEFAULT_DEPTH_URL, DEFAULT_ZENOH_ENDPOINT
from metricslam.errors import ConfigError, validation_problems

#: service variables that moved into the system config, and where they live now
RETIRED_ENV = {"SLAM_PRESET": "METRICSLAM_VO__PRESET", "SLAM_USE_SCALE": "METRICSLAM_DEPTH__USE_SCALE",
               "SLAM_QUEUE_SIZE": "METRICSLAM_QUEUES__FRAMES"}


class SlamServiceSettings(BaseSettings):
    """Service-level settings (network, depth client, status, viewer). Logged at start-up.

    Attributes:
        zenoh_endpoint: router endpoint to connect to, e.g. ``tcp/127.0.0.1:7447``.
        zenoh_mode: ``client`` (connect to a router) or ``peer``.
        depth_url: base URL of the depth service (default: where a bare ``metricslam
            depth-service`` listens, :data:`metricslam.endpoints.DEFAULT_DEPTH_URL`); None
            runs the depth model in-process (learned scale on/off is ``depth.use_scale`` of the
            system config).
        session_kind: ``pipeline`` (the real SLAM core) or ``identity`` (transport only:
            identity poses, for transport benchmarks).
        status_period_s: how often ``…/status`` is published (and the depth service probed).
        depth_timeout_s / depth_connect_timeout_s / depth_retries / depth_backoff_s: HTTP client.
        keyframe_images: attach the keyframe image to ``…/keyframe`` messages.
        frame_key_expr: which cameras this worker serves, e.g. ``metricslam/fleet-a-$*/frame``
            (partition cameras across SLAM workers; docs/deployment.md).
        rerun: live view with rerun-sdk: ``web`` or a ``.rrd`` path (needs the ``viz`` extra).
        ros2: also speak ROS 2 over Zenoh as rmw_zenoh does (``SLAM_ROS2=1``; the ``ros``
            extra): publish ``/metricslam/<cam>/odom``, ``…/pose``, ``…/path``, ``…/landmarks``
            and take ``…/image`` + ``…/camera_info`` as input (docs/ros2.md).
        ros2_domain_id: ``ROS_DOMAIN_ID`` of those topics (``SLAM_ROS2_DOMAIN_ID``).
        ros2_node_name: the ROS 2 node the topics belong to (``ros2 node list``).
        ros2_position_sigma_m / ros2_rotation_sigma_rad: the NOMINAL standard deviations put on
            the diagonal of ``Odometry.pose.covariance`` once metric scale is established (the
            SLAM computes no per-frame marginal covariance; docs/ros2.md says why). Before that
            the position variance is 1e6 m² (scale unknown).
        max_cameras: cameras served at once; a new camera beyond it is refused (its frames
            are dropped and counted, a ``camera_refused`` status is published on its status key).
        camera_idle_timeout_s: a camera with no frame for this long is closed (thread, session
            and memory freed; a ``camera_closed`` status is published).
        closed_trajectory_ttl_s / max_closed_trajectories: how long, and for how many closed
            cameras, the final trajectory stays answerable on ``…/trajectory``.
        max_session_keyframes: a session that reaches this many keyframes is closed and the
            camera continues in a new linked session (``session_rolled_over``): bounds a
            camera's memory (the global graph and place-recognition database grow with
            keyframes); None: never.
        malloc_arenas: glibc malloc arenas of the service process (``mallopt(M_ARENA_MAX)``,
            :mod:`metricslam_slam.service.memory`); 0: glibc's default (8 per core). 2: the
            soak's RSS floor stops rising across roll-overs
            (``bench/results/slam_service_soak_10000.md``).
        heap_trim_period_s: return free heap pages to the OS this often (``malloc_trim``, a few
            ms, from the status thread), and after each batch re-solve of a global graph (each
            accepted loop: it frees the old ISAM2); 0: only when a session closes. 10: the 10,000-frame
            soak's peak RSS above warm-up fell by ~20 MiB at the same wall time
            (``bench/results/slam_service_soak_10000.md`` now and at commit f04685c).
        state_dir: where each camera's trajectory is persisted (``<camera_id>.poses.jsonl``); a
            restarted service continues a known camera from its last pose
            (``session_restarted``). None: nothing survives a restart.
        hang_timeout_s: the service's own watchdog ends the process (exit 70) when a camera has
            been stuck on one frame, or the status loop has not ticked, for this long, so that
            compose (``restart: unless-stopped``) or Kubernetes restarts it
            (:mod:`metricslam_slam.service.watchdog`); 0: never (the heartbeat file, if set, is
            still written).
        map: a saved map (``metricslam run --save-map``) every camera session relocalizes into;
            poses are in the map frame from then on (``frame_id "map"``). A map that cannot be
            used is one error line and the service runs without it (docs/maps.md). None: no map.
        heartbeat_file: the watchdog rewrites this file after each check that found nothing hung;
            the Kubernetes liveness probe (``python -m metricslam_slam.supervisor.healthcheck
            --alive``) fails when it is stale. None: no file.
    """

    model_config = SettingsConfigDict(env_prefix="SLAM_", frozen=True, extra="forbid")

    zenoh_endpoint: str = DEFAULT_ZENOH_ENDPOINT
    zenoh_mode: Literal["client", "peer"] = "client"
    depth_url: str | None = DEFAULT_DEPTH_URL
    session_kind: Literal["pipeline", "identity"] = "pipeline"
    status_period_s: float = Field(default=1.0, gt=0)
    depth_timeout_s: float = Field(default=5.0, gt=0)
    depth_connect_timeout_s: float = Field(default=0.5, gt=0)
    depth_retries: int = Field(default=2, ge=0, le=10)
    depth_backoff_s: float = Field(default=0.2, ge=0)
    keyframe_images: bool = False
    frame_key_expr: str = "metricslam/*/frame"
    rerun: str | None = None
    ros2: bool = False
    ros2_domain_id: int = Field(default=0, ge=0)
    ros2_node_name: str = Field(default="metricslam_slam", pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")
    ros2_position_sigma_m: float = Field(default=0.5, gt=0)
    ros2_rotation_sigma_rad: float = Field(default=0.02, gt=0)
    max_cameras: int = Field(default=8, ge=1)
    camera_idle_timeout_s: float = Field(default=120.0, gt=0)
    closed_trajectory_ttl_s: float = Field(default=3600.0, ge=0)
    max_closed_trajectories: int = Field(default=32, ge=0)
    max_session_keyframes: int | None = Field(default=1000, ge=10)
    malloc_arenas: int = Field(default=2, ge=0)
    heap_trim_period_s: float = Field(default=10.0, ge=0)
    state_dir: Path | None = None
    hang_timeout_s: float = Field(default=120.0, ge=0)
    heartbeat_file: Path | None = None
    map: Path | None = None


def load_settings(**overrides: object) -> SlamServiceSettings:
    """Settings from the environment (``SLAM_*``) with ``overrides`` (the command-line flags that
    were given; a None value is a value, e.g. ``depth_url=None`` for the in-process model) on top.

    Raises:
        ConfigError: a value is invalid, in one line naming each field and its variable (or the
            command line), e.g. ``SLAM_MAX_CAMERAS=-1``.
    """
    try:
        return SlamServiceSettings(**overrides)
    except ValidationError as exc:
        raise ConfigError("invalid slam-service settings: "
                          + validation_problems(exc, env_prefix="SLAM_", from_flags=overrides)) from exc


def check_retired_environment(env: Mapping[str, str] | None = None) -> None:
    """Refuse ``SLAM_*`` variables that moved into the system config (pydantic-settings would
    ignore them silently, e.g. a ``SLAM_USE_SCALE=false`` would run WITH learned scale).

    Raises:
        ConfigError: naming each retired variable and its replacement.
    """
    env = os.environ if env is None else env
    stale = sorted(set(env) & set(RETIRED_ENV))
    if stale:
        raise ConfigError("retired environment variable(s) " + ", ".join(
            f"{name} (use {RETIRED_ENV[name]})" for name in stale)
            + ": algorithm settings of the SLAM sessions are the system config now")
