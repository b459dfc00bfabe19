"""``metricslam up``: start the local stack (zenoh router, depth service, SLAM service).

Example::

    metricslam up --zenoh-endpoint tcp/127.0.0.1:7447 --depth-port 8100
    metricslam replay SEQ --zenoh-endpoint tcp/127.0.0.1:7447 --rate 10     # in another shell

Every port the stack binds is checked first: a taken one is refused (exit code 1) with a message
naming it and the flag that moves it. Children are supervised: restarted if they die, or if
they stop answering their health probe (router query, depth ``/healthz``, SLAM health query) for
``--hang-timeout`` seconds, with exponential backoff while they keep failing; Ctrl-C / SIGTERM
stops them all. Without ``--log-dir`` the last lines of each child's output are kept and printed
when it fails. The SLAM service always has a state directory (``--state-dir``, else
``SLAM_STATE_DIR``, else a temporary folder removed when ``up`` stops), so a restarted SLAM child
continues each camera's trajectory as a new linked segment instead of starting over at the origin.
"""

from __future__ import annotations

import argparse

from metricslam.endpoints import DEFAULT_DEPTH_HOST, DEFAULT_DEPTH_PORT, DEFAULT_ZENOH_ENDPOINT
from metricslam_cli.extras import require
from metricslam_cli.scale_options import add_scale_options, log_scale_sources, scale_flags


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "up", help="start router + depth service + SLAM service locally",
        description="Starts a Zenoh router, the depth service and the SLAM service as child "
        "processes, waits until each is ready, prints the endpoints, restarts a child that dies, "
        "and stops everything on SIGINT/SIGTERM. Refuses to start when a port it would bind "
        "(router, depth service) is taken.")
    p.add_argument("--zenoh-endpoint", default=DEFAULT_ZENOH_ENDPOINT, metavar="EP",
                   help=f"router listen endpoint (default {DEFAULT_ZENOH_ENDPOINT})")
    p.add_argument("--depth-port", type=int, default=DEFAULT_DEPTH_PORT, metavar="P",
                   help=f"depth service port (default {DEFAULT_DEPTH_PORT})")
    p.add_argument("--depth-host", default=DEFAULT_DEPTH_HOST, help="depth service interface")
    p.add_argument("--no-scale", action="store_true", help="no depth service, no learned scale")
    p.add_argument("--preset", choices=("kitti", "euroc", "tum", "synth"),
                   help="VO preset for the SLAM service (default: the config's vo.preset, else kitti)")
    p.add_argument("--config", metavar="FILE.yaml",
                   help="SLAM service system config (the file `metricslam run --config` takes)")
    p.add_argument("--session", dest="session_kind", default="pipeline",
                   choices=("pipeline", "identity"), help="SLAM session kind (identity: transport only)")
    p.add_argument("--log-dir", metavar="DIR",
                   help="write each child's output to DIR/<name>.log (else only its last lines are "
                        "kept, and printed when it fails)")
    p.add_argument("--restart-delay", type=float, default=1.0, metavar="S",
                   help="seconds before restarting a child that died; doubles while it keeps "
                        "crashing (default 1)")
    p.add_argument("--restart-delay-max", type=float, default=30.0, metavar="S",
                   help="longest wait between restarts of a crashing child (default 30)")
    p.add_argument("--hang-timeout", type=float, default=20.0, metavar="S",
                   help="kill and restart a child whose health probe has not answered for S "
                        "seconds (router: a zenoh query, depth: /healthz, SLAM: its health query; "
                        "default 20; 0: only restart children that exit)")
    p.add_argument("--probe-period", type=float, default=2.0, metavar="S",
                   help="seconds between health probes (default 2)")
    p.add_argument("--state-dir", metavar="DIR",
                   help="where the SLAM service keeps each camera's trajectory, so a restarted SLAM "
                        "service continues it (default: SLAM_STATE_DIR, else a temporary folder "
                        "removed when up stops)")
    p.add_argument("--rerun", metavar="TARGET",
                   help="SLAM live view: 'web' or FILE.rrd (needs metricslam[viz])")
    p.add_argument("--map", metavar="MAP",
                   help="the SLAM service's saved map (SLAM_MAP; docs/maps.md): cameras relocalize into it")
    add_scale_options(p)  # passed on to the SLAM service (docs/ground_scale.md)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    require(*(() if args.no_scale else ("depth-service",)), "slam-service", command="up")

    import logging
    import os
    import signal
    import tempfile
    from pathlib import Path

    from metricslam.slam.config_file import load_system_config
    from metricslam.slam.system_config import LIVE_PROFILE
    from metricslam_slam.supervisor.launcher import Stack

    # the SLAM child's system config, checked before anything starts (slam-service loads it so)
    _, scale_overrides = scale_flags(args)
    config = load_system_config(args.config, profile=LIVE_PROFILE,
                                overrides={**({"vo": {"preset": args.preset}} if args.preset else {}),
                                           **scale_overrides})
    log_scale_sources(config, logging.getLogger("metricslam.up"))
    if args.log_dir:
        Path(args.log_dir).mkdir(parents=True, exist_ok=True)
    if args.map:  # the SLAM child reads it from its environment (a bad map: it runs without one)
        os.environ["SLAM_MAP"] = str(Path(args.map).resolve())
    # without state, a SLAM service the supervisor restarts starts its cameras over at the origin
    state_dir = args.state_dir or os.environ.get("SLAM_STATE_DIR") or None
    scratch = None if state_dir else tempfile.TemporaryDirectory(prefix="metricslam-up-state-")
    stack = Stack(args.zenoh_endpoint, depth_port=args.depth_port, depth_host=args.depth_host,
                  use_scale=not args.no_scale, preset=args.preset, session_kind=args.session_kind,
                  log_dir=args.log_dir, restart_delay_s=args.restart_delay, rerun=args.rerun,
                  config_path=args.config, restart_delay_max_s=args.restart_delay_max,
                  hang_timeout_s=args.hang_timeout, probe_period_s=args.probe_period,
                  state_dir=state_dir or scratch.name, scale_sources=args.scale_sources,
                  mount_height_m=args.mount_height)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stack.request_stop())

    def ready(child) -> None:
        print(f"{child.name:<14} ready  pid {child.process.pid:<7} {child.where}", flush=True)

    def restarted(child) -> None:
        print(f"{child.name:<14} restarted  pid {child.process.pid:<7} (restart #{child.restarts})",
              flush=True)

    def hung(child, silent_s: float) -> None:
        print(f"{child.name:<14} hung  no health answer for {silent_s:.1f} s; killed, restarting",
              flush=True)

    try:
        stack.start(on_ready=ready)
        print(f"UP: publish frames on metricslam/<camera_id>/frame via {args.zenoh_endpoint}; "
              "Ctrl-C stops", flush=True)
        try:
            stack.supervise(on_restart=restarted, on_hung=hung)
        finally:
            stack.stop()
            print("stopped", flush=True)
    finally:
        if scratch is not None:
            scratch.cleanup()
    return 0
