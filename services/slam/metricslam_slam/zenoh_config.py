"""Zenoh session configs with explicit endpoints and multicast scouting off.

DESIGN.md measured that multicast discovery is unreliable on our machines, so every session in
the stack names its endpoint: the router ``listen``s, everyone else ``connect``s.
"""

from __future__ import annotations

import json

import zenoh

from metricslam.errors import ServiceError


def check_endpoint(endpoint: str) -> str:
    """``tcp/HOST:PORT`` (or ``udp/…``, ``quic/…``); raises :class:`ServiceError` otherwise."""
    proto, _, rest = endpoint.partition("/")
    host, _, port = rest.rpartition(":")
    if proto not in ("tcp", "udp", "quic", "tls") or not host or not port.isdigit():
        raise ServiceError(f"zenoh endpoint {endpoint!r} must look like tcp/127.0.0.1:7447")
    return endpoint


def session_config(mode: str, *, listen: list[str] = (), connect: list[str] = ()) -> zenoh.Config:
    """A zenoh config in ``mode`` (router|peer|client) with explicit endpoints."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    if listen:
        config.insert_json5("listen/endpoints", json.dumps([check_endpoint(e) for e in listen]))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps([check_endpoint(e) for e in connect]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return config


def open_client(endpoint: str, mode: str = "client") -> zenoh.Session:
    """Open a session that connects to the router at ``endpoint``."""
    try:
        return zenoh.open(session_config(mode, connect=[endpoint]))
    except zenoh.ZError as exc:
        raise ServiceError(f"cannot connect to the zenoh router at {endpoint}: {exc}; "
                           "is `metricslam up` (or a zenoh router) running there?") from None
