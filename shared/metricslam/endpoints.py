"""Default network endpoints of the stack, defined once for every side that needs them.

The depth service listens on ``DEFAULT_DEPTH_HOST:DEFAULT_DEPTH_PORT`` and the SLAM service's
default ``depth_url`` is :data:`DEFAULT_DEPTH_URL`, so a bare ``metricslam depth-service`` and a
bare ``metricslam slam-service`` find each other. Override with ``DEPTH_PORT`` (depth service)
and ``SLAM_DEPTH_URL`` (SLAM service), or the matching flags.

Pure constants: importing this pulls no web framework (the core may import it).
"""

from __future__ import annotations

#: interface the depth service binds by default (loopback: not exposed unless asked)
DEFAULT_DEPTH_HOST = "127.0.0.1"
#: TCP port of the depth service (``metricslam depth-service``, ``metricslam up``, compose)
DEFAULT_DEPTH_PORT = 8100
#: router endpoint the SLAM service and the client tools connect to by default
DEFAULT_ZENOH_ENDPOINT = "tcp/127.0.0.1:7447"


def depth_url(host: str = DEFAULT_DEPTH_HOST, port: int = DEFAULT_DEPTH_PORT) -> str:
    """Base URL of a depth service, e.g. ``http://127.0.0.1:8100``."""
    return f"http://{host}:{int(port)}"


#: where the SLAM service looks for the depth service unless told otherwise
DEFAULT_DEPTH_URL = depth_url()
