"""A Zenoh router for the local stack: a Python session in ``router`` mode.

There is no ``zenohd`` binary on PyPI or Debian; a zenoh-python session opened in router mode
routes between clients just the same. ``python -m metricslam_slam.supervisor.router --listen EP`` runs one
until SIGINT/SIGTERM (this is what ``metricslam up`` starts) and answers the queryable
``metricslam/_router/health`` itself, so the supervisor can tell a router that routes from one
that merely holds its port (a stopped process still accepts TCP connections). In compose, the
upstream ``eclipse/zenoh`` image plays this part.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import time

import zenoh

from metricslam.errors import ServiceError
from metricslam.wire.keys import ROUTER_HEALTH_KEY
from metricslam_slam.zenoh_config import ZenohAccess, session_config

log = logging.getLogger(__name__)


def open_router(listen: list[str] | str, connect: list[str] = (),
                access: ZenohAccess | None = None) -> zenoh.Session:
    """Open a router session listening on ``listen`` (and meshed with routers in ``connect``).

    Args:
        access: authentication and ACL (``users_file``, ``pose_publishers``); None reads
            ``ZENOH_ACCESS_*`` from the environment (:mod:`metricslam_slam.zenoh_config`).

    Raises:
        ServiceError: the endpoint cannot be bound (port in use?), or a bad access setting.
    """
    listen = [listen] if isinstance(listen, str) else list(listen)
    try:
        return zenoh.open(session_config("router", listen=listen, connect=list(connect), access=access))
    except zenoh.ZError as exc:
        raise ServiceError(f"cannot start a zenoh router on {listen}: {exc}; is the port in use?") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="zenoh router (Python session in router mode)")
    parser.add_argument("--listen", action="append", required=True, help="endpoint, e.g. tcp/127.0.0.1:7447 (tcp/0.0.0.0:7447: every interface)")
    parser.add_argument("--connect", action="append", default=[], help="other routers to mesh with")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s router: %(message)s")
    signalled: list[int] = []  # a plain list: a handler must not take a lock the main thread may hold
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: signalled.append(signum))
    try:
        session = open_router(args.listen, args.connect)
    except ServiceError as exc:
        print(f"router: error: {exc}", file=sys.stderr)
        return 1
    answer = json.dumps({"ready": True, "pid": os.getpid()}).encode()
    health = session.declare_queryable(ROUTER_HEALTH_KEY,
                                       lambda query: query.reply(ROUTER_HEALTH_KEY, answer))
    access = ZenohAccess()
    log.info("zenoh router listening on %s; authentication %s, pose publishers: %s", ", ".join(args.listen),
             f"on ({access.users_file})" if access.users_file else "off",
             access.pose_publishers or "anyone")
    print("READY", flush=True)
    # polled, never an untimed wait: SIGTERM (e.g. the parent-death signal) may land on a zenoh
    # thread, and Python runs its handler only when the main thread wakes up
    while not signalled:
        time.sleep(0.2)
    health.undeclare()
    session.close()
    log.info("zenoh router stopped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
