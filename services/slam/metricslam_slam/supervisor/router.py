"""A Zenoh router for the local stack: a Python session in ``router`` mode.

There is no ``zenohd`` binary on PyPI or Debian; a zenoh-python session opened in router mode
routes between clients just the same. ``python -m metricslam_slam.supervisor.router --listen EP`` runs one
until SIGINT/SIGTERM (this is what ``metricslam up`` starts). In compose, the upstream
``eclipse/zenoh`` image plays this part.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

import zenoh

from metricslam.errors import ServiceError
from metricslam_slam.zenoh_config import session_config

log = logging.getLogger(__name__)


def open_router(listen: list[str] | str, connect: list[str] = ()) -> zenoh.Session:
    """Open a router session listening on ``listen`` (and meshed with routers in ``connect``).

    Raises:
        ServiceError: the endpoint cannot be bound (port in use?).
    """
    listen = [listen] if isinstance(listen, str) else list(listen)
    try:
        return zenoh.open(session_config("router", listen=listen, connect=list(connect)))
    except zenoh.ZError as exc:
        raise ServiceError(f"cannot start a zenoh router on {listen}: {exc}; is the port in use?") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="zenoh router (Python session in router mode)")
    parser.add_argument("--listen", action="append", required=True, help="endpoint, e.g. tcp/0.0.0.0:7447")
    parser.add_argument("--connect", action="append", default=[], help="other routers to mesh with")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s router: %(message)s")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        session = open_router(args.listen, args.connect)
    except ServiceError as exc:
        print(f"router: error: {exc}", file=sys.stderr)
        return 1
    log.info("zenoh router listening on %s", ", ".join(args.listen))
    print("READY", flush=True)
    stop.wait()
    session.close()
    log.info("zenoh router stopped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
