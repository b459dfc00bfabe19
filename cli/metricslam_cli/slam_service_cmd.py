"""``metricslam slam-service``: the SLAM service over Zenoh.

Example::

    metricslam slam-service --zenoh-endpoint tcp/127.0.0.1:7447 --depth-url http://127.0.0.1:8100
    metricslam slam-service --config my_camera.yaml      # the same file `metricslam run` takes

Subscribes ``metricslam/*/frame``; publishes ``…/pose`` (every frame), ``…/keyframe``,
``…/status``, ``…/path``, ``…/landmarks``, ``…/keyframe_depth``; answers ``…/trajectory``;
with ``--ros2`` the same outputs as ROS 2 topics (docs/ros2.md). Service flags override ``SLAM_*`` environment variables;
the sessions' :class:`~metricslam.slam.system_config.SystemConfig` comes from ``--config`` (or
``METRICSLAM_CONFIG``), then ``METRICSLAM_*`` variables, then ``--preset`` / ``--no-scale`` /
``--queue-size``.
"""

from __future__ import annotations

import argparse

from metricslam.endpoints import DEFAULT_DEPTH_URL
from metricslam_cli.extras import require
from metricslam_cli.scale_options import add_scale_options, log_scale_sources, scale_flags


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "slam-service", help="run the SLAM service (zenoh in/out, one session per camera)",
        description="Runs one SLAM session per camera id seen on metricslam/<id>/frame and "
        "publishes poses, keyframes and status over Zenoh. Flags override SLAM_* env variables.")
    p.add_argument("--zenoh-endpoint", metavar="EP", help="router endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--depth-url", metavar="URL",
                   help=f"depth service base URL (default {DEFAULT_DEPTH_URL}, where a bare "
                        "`metricslam depth-service` listens; env SLAM_DEPTH_URL; 'none': "
                        "in-process model)")
    p.add_argument("--config", metavar="FILE.yaml",
                   help="system configuration, the format `metricslam run --config` takes "
                        "(default $METRICSLAM_CONFIG); METRICSLAM_* variables override it")
    p.add_argument("--no-scale", action="store_true", help="no learned scale factors (baseline)")
    p.add_argument("--preset", choices=("kitti", "euroc", "tum", "synth"),
                   help="VO preset (default: the config's vo.preset, else kitti)")
    p.add_argument("--queue-size", type=int,
                   help="frames buffered per camera, drop-oldest (default: the config's queues.frames)")
    p.add_argument("--session", dest="session_kind", choices=("pipeline", "identity"),
                   help="pipeline (default) or identity (transport only, for benchmarks)")
    p.add_argument("--status-period", dest="status_period_s", type=float, metavar="S",
                   help="seconds between status messages")
    p.add_argument("--keyframe-images", action="store_true", default=None,
                   help="attach images to keyframe messages")
    p.add_argument("--frames-key", dest="frame_key_expr", metavar="KEYEXPR",
                   help="cameras this worker serves (default metricslam/*/frame; e.g. "
                   "'metricslam/fleet-a-$*/frame')")
    p.add_argument("--rerun", metavar="TARGET",
                   help="live view: 'web' (viewer on localhost) or FILE.rrd (needs metricslam[viz])")
    p.add_argument("--ros2", action="store_true", default=None,
                   help="also publish/subscribe ROS 2 topics as rmw_zenoh does (odom, pose, path, "
                        "landmarks out; image + camera_info in; env SLAM_ROS2=1; needs "
                        "metricslam[ros]; docs/ros2.md)")
    p.add_argument("--ros-domain-id", dest="ros2_domain_id", type=int, metavar="N",
                   help="ROS_DOMAIN_ID of the ROS 2 topics (default 0; env SLAM_ROS2_DOMAIN_ID)")
    p.add_argument("--state-dir", metavar="DIR",
                   help="persist each camera's trajectory here; a restarted service continues it "
                        "(env SLAM_STATE_DIR; docs/deployment.md)")
    p.add_argument("--max-cameras", type=int, metavar="N",
                   help="cameras served at once; more are refused (default 8; env SLAM_MAX_CAMERAS)")
    p.add_argument("--map", metavar="MAP",
                   help="a saved map (run --save-map) every camera relocalizes into; poses in the map "
                        "frame from then on; an unusable map is logged and not used (env SLAM_MAP; "
                        "docs/maps.md)")
    add_scale_options(p)
    p.set_defaults(func=run)
    return p


def config_from_args(args: argparse.Namespace):
    """The sessions' :class:`~metricslam.slam.system_config.SystemConfig`: class defaults → the
    live profile (:data:`~metricslam.slam.system_config.LIVE_PROFILE`: initial metric scale on) →
    ``--config`` (or ``$METRICSLAM_CONFIG``) → ``METRICSLAM_*`` → ``--preset`` / ``--queue-size``
    / ``--no-scale`` — the loader ``metricslam run`` uses, without its offline depth queue."""
    from metricslam.slam.config_file import load_system_config
    from metricslam.slam.system_config import LIVE_PROFILE

    flags: dict = {}
    if args.preset is not None:
        flags["vo"] = {"preset": args.preset}
    if args.queue_size is not None:
        flags["queues"] = {"frames": args.queue_size}
    if args.no_scale:
        flags["depth"] = {"use_scale": False}
    _, scale_overrides = scale_flags(args)
    return load_system_config(args.config, profile=LIVE_PROFILE, overrides={**flags, **scale_overrides})


def run(args: argparse.Namespace) -> int:
    require("slam-service", command="slam-service")

    import signal

    from metricslam_slam.service.settings import load_settings
    from metricslam_slam.service.slam_service import SlamService

    overrides = {k: getattr(args, k) for k in ("zenoh_endpoint", "session_kind", "status_period_s",
                                                 "keyframe_images", "rerun", "frame_key_expr",
                                                 "ros2", "ros2_domain_id", "state_dir", "max_cameras", "map")
                 if getattr(args, k) is not None}
    if args.depth_url is not None:
        overrides["depth_url"] = None if args.depth_url.lower() == "none" else args.depth_url
    config = config_from_args(args)  # before any network: a bad file fails fast
    import logging

    log_scale_sources(config, logging.getLogger("metricslam.slam_service"))
    settings = load_settings(**overrides)
    from metricslam_slam.service.memory import limit_malloc_arenas

    limit_malloc_arenas(settings.malloc_arenas)  # before the service's threads start
    service = SlamService(settings, config=config)
    # the handler only appends to a list: setting the service's Event from a handler can deadlock
    # on the lock its wait() holds; and the wait is polled, because a signal that lands on a
    # zenoh thread runs its Python handler only when the main thread wakes up
    signalled: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: signalled.append(signum))
    service.start()
    print("READY", flush=True)
    try:
        while not signalled and not service.wait(0.5):
            pass
    finally:
        service.stop()
    return 0
