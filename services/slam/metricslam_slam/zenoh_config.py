"""Zenoh session configs: explicit endpoints, multicast scouting off, loopback unless told,
optional user/password authentication and an access-control list.

DESIGN.md measured that multicast discovery is unreliable on our machines, so every session in
the stack names its endpoint: the router ``listen``s, everyone else ``connect``s. A peer-mode
session also listens (zenoh's default is every interface on a random port); here it listens on
``tcp/127.0.0.1:0`` unless ``listen`` says otherwise.

Access control (:class:`ZenohAccess`, environment ``ZENOH_ACCESS_*``, off by default for local
use; docs/deployment.md "Access control"): a router given ``users_file`` (zenoh's ``user:password``
dictionary) refuses sessions without valid credentials; every other session (SLAM service, CLI
tools, probes) presents ``user`` / ``password``. With ``pose_publishers`` as well, the router's
ACL lets only those users publish the SLAM service's outputs (``…/pose``, ``…/keyframe``,
``…/status``, map topics) and serve its queryables: a camera's credentials cannot forge poses.
"""

from __future__ import annotations

import json
from pathlib import Path

import zenoh
from pydantic import SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

from metricslam.errors import ServiceError
from metricslam.wire import keys

#: what only the SLAM service publishes (``put``/``delete``) ...
SERVICE_OUTPUT_TOPICS = ("pose", "keyframe", "status", "path", "landmarks", "keyframe_depth")
#: ... and serves (``declare_queryable``)
SERVICE_QUERYABLES = (keys.wildcard("trajectory"), keys.HEALTH_KEY)


class ZenohAccess(BaseSettings):
    """Zenoh authentication and access control, from ``ZENOH_ACCESS_*`` (all empty: off).

    Attributes:
        user / password: credentials this process presents to the router
            (``ZENOH_ACCESS_USER``, ``ZENOH_ACCESS_PASSWORD``).
        users_file: router only: zenoh's credentials dictionary, one ``user:password`` per line;
            set, the router refuses sessions without valid credentials.
        pose_publishers: router only: comma-separated users allowed to publish the SLAM
            service's outputs and serve its queryables (e.g. ``slam``); every other user of
            ``users_file`` is denied exactly that (``ZENOH_ACCESS_POSE_PUBLISHERS=slam``).
    """

    model_config = SettingsConfigDict(env_prefix="ZENOH_ACCESS_", frozen=True, extra="forbid")

    user: str | None = None
    password: SecretStr | None = None
    users_file: Path | None = None
    pose_publishers: str = ""

    @property
    def pose_publisher_names(self) -> list[str]:
        return [name.strip() for name in self.pose_publishers.split(",") if name.strip()]


def check_endpoint(endpoint: str) -> str:
    """``tcp/HOST:PORT`` (or ``udp/…``, ``quic/…``); raises :class:`ServiceError` otherwise."""
    proto, _, rest = endpoint.partition("/")
    host, _, port = rest.rpartition(":")
    if proto not in ("tcp", "udp", "quic", "tls") or not host or not port.isdigit():
        raise ServiceError(f"zenoh endpoint {endpoint!r} must look like tcp/127.0.0.1:7447")
    return endpoint


def read_users(users_file: Path) -> list[str]:
    """User names of a zenoh credentials dictionary (``user:password`` lines)."""
    try:
        lines = Path(users_file).read_text().splitlines()
    except OSError as exc:
        raise ServiceError(f"cannot read the zenoh users file {users_file}: {exc}") from None
    users = [line.split(":", 1)[0].strip() for line in lines if ":" in line and line.strip()]
    if not users:
        raise ServiceError(f"zenoh users file {users_file} has no 'user:password' line")
    return users


def pose_acl(users: list[str], pose_publishers: list[str]) -> dict:
    """The router's ``access_control`` section: users other than ``pose_publishers`` may not
    publish the service's outputs nor declare its queryables; everything else is allowed."""
    unknown = sorted(set(pose_publishers) - set(users))
    if unknown:
        raise ServiceError(f"pose publisher(s) {unknown} are not in the users file")
    others = sorted(set(users) - set(pose_publishers))
    rules = [{"id": "service-outputs", "permission": "deny", "flows": ["ingress"],
              "messages": ["put", "delete"], "key_exprs": [keys.wildcard(t) for t in SERVICE_OUTPUT_TOPICS]},
             {"id": "service-queryables", "permission": "deny", "flows": ["ingress"],
              "messages": ["declare_queryable"], "key_exprs": list(SERVICE_QUERYABLES)}]
    if not others:  # nobody to deny
        return {"enabled": False}
    return {"enabled": True, "default_permission": "allow", "rules": rules,
            "subjects": [{"id": "not-pose-publishers", "usernames": others}],
            "policies": [{"rules": ["service-outputs", "service-queryables"],
                          "subjects": ["not-pose-publishers"]}]}


def session_config(mode: str, *, listen: list[str] = (), connect: list[str] = (),
                   access: ZenohAccess | None = None) -> zenoh.Config:
    """A zenoh config in ``mode`` (router|peer|client) with explicit endpoints.

    Args:
        access: authentication / ACL; None reads ``ZENOH_ACCESS_*`` from the environment.

    Raises:
        ServiceError: a bad endpoint, an unreadable users file, an ACL naming unknown users.
    """
    access = ZenohAccess() if access is None else access
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    if not listen and mode == "peer":
        listen = ["tcp/127.0.0.1:0"]  # zenoh's default would be every interface
    if listen:
        config.insert_json5("listen/endpoints", json.dumps([check_endpoint(e) for e in listen]))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps([check_endpoint(e) for e in connect]))
    config.insert_json5("scouting/multicast/enabled", "false")
    usrpwd: dict = {}
    if access.user:
        usrpwd = {"user": access.user,
                  "password": access.password.get_secret_value() if access.password else ""}
    if mode != "client" and access.users_file is not None:
        usrpwd["dictionary_file"] = str(access.users_file)
        if access.pose_publisher_names:
            config.insert_json5("access_control", json.dumps(
                pose_acl(read_users(access.users_file), access.pose_publisher_names)))
        else:
            read_users(access.users_file)  # fail here, not inside zenoh
    elif mode != "client" and access.pose_publisher_names:
        raise ServiceError("ZENOH_ACCESS_POSE_PUBLISHERS needs ZENOH_ACCESS_USERS_FILE: the ACL "
                           "tells users apart by their authenticated user name")
    if usrpwd:
        config.insert_json5("transport/auth/usrpwd", json.dumps(usrpwd))
    return config


def open_client(endpoint: str, mode: str = "client", access: ZenohAccess | None = None) -> zenoh.Session:
    """Open a session that connects to the router at ``endpoint`` (credentials from ``access``,
    default ``ZENOH_ACCESS_*``)."""
    try:
        return zenoh.open(session_config(mode, connect=[endpoint], access=access))
    except zenoh.ZError as exc:
        raise ServiceError(f"cannot connect to the zenoh router at {endpoint}: {exc}; "
                           "is `metricslam up` (or a zenoh router) running there, and if it checks "
                           "credentials, are ZENOH_ACCESS_USER / ZENOH_ACCESS_PASSWORD right?") from None
