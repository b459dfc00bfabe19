"""The names and metadata rmw_zenoh (ROS 2's Zenoh middleware) uses, so that our Zenoh
publishers and subscribers are ordinary ROS 2 topics to a node running on rmw_zenoh.

Written from rmw_zenoh's design document (``docs/design.md`` of ros2/rmw_zenoh, sections
"Topic and Service name mapping to Zenoh key expressions", "Graph Cache" and "Publishers"):

* **data key expression** — ``<domain_id>/<fully qualified topic, no leading or trailing
  slash>/<DDS type name>/<type hash>``, e.g.
  ``0/metricslam/cam0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_3cc9…``;
* **liveliness tokens** (the ROS graph: ``ros2 node list``, ``ros2 topic list/info``) —
  node: ``@ros2_lv/<domain>/<zenoh session id>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>``;
  publisher / subscription: ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP|MS/<enclave>/
  <namespace>/<node>/<topic>/<DDS type name>/<type hash>/<qos>``, where enclave, namespace and
  topic are "mangled" (every ``/`` becomes ``%``; an empty or root name is ``%``);
* **qos chunk** — ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan
  s>,<ns>:<liveliness>,<lease s>,<ns>`` with rmw's enum values, a field left empty when it equals
  rmw_zenoh's default (reliable, volatile, keep-last, depth 42, infinite durations, automatic):
  our keep-last-10 publishers are ``::,10:,:,:,,``;
* **sample attachment** — every published sample carries 33 bytes: sequence number (int64
  little-endian), source timestamp (int64 little-endian, ns since the UNIX epoch), the GID length
  (one byte, 16) and the 16-byte publisher GID.

Pure string/byte functions; the Zenoh side is ``metricslam_slam.service.ros2_bridge``.
"""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass

from metricslam.errors import CodecError
from metricslam.ros2.typestore import dds_type_name, type_hash

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"
GID_BYTES = 16
_ATTACHMENT = struct.Struct("<qqB")
_TOKEN_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
# rmw/types.h enum values
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
_DEFAULT_DEPTH = 42  # rmw_zenoh's depth when a profile asks for 0 ("system default")


@dataclass(frozen=True)
class Qos:
    """The QoS a ROS 2 entity advertises (deadline, lifespan and liveliness at their defaults)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10

    def key(self) -> str:
        """The compact qos chunk of a liveliness token (module docstring)."""
        def opt(value: int, default: int) -> str:
            return "" if value == default else str(value)

        return (f"{opt(self.reliability, RELIABLE)}:{opt(self.durability, VOLATILE)}:"
                f"{opt(self.history, KEEP_LAST)},{opt(self.depth, _DEFAULT_DEPTH)}:,:,:,,")


@dataclass(frozen=True)
class Node:
    """A ROS 2 node as the graph sees it.

    Attributes:
        domain_id: ``ROS_DOMAIN_ID`` (0..232 on DDS; any non-negative int on Zenoh).
        zid: the Zenoh session id, as Zenoh prints it (lower-case hex).
        node_id: the node's id within the session.
        name: node name (one ROS name token).
        namespace: ``/`` or ``/a/b``.
        enclave: SROS enclave, ``/`` when unset.
    """

    domain_id: int
    zid: str
    node_id: int
    name: str
    namespace: str = "/"
    enclave: str = "/"

    def __post_init__(self) -> None:
        if self.domain_id < 0:
            raise CodecError(f"ROS domain id must be >= 0, got {self.domain_id}")
        if not _TOKEN_RE.match(self.name):
            raise CodecError(f"invalid ROS node name {self.name!r}")
        if not self.zid or not re.fullmatch(r"[0-9a-f]+", self.zid):
            raise CodecError(f"zenoh session id {self.zid!r} is not lower-case hex")

    def _prefix(self, entity_id: int, kind: str) -> str:
        return (f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{entity_id}/{kind}/"
                f"{mangle(self.enclave)}/{mangle(self.namespace)}/{self.name}")

    def token(self) -> str:
        """The node's liveliness token (``…/NN/…``; its entity id is its node id)."""
        return self._prefix(self.node_id, NODE)

    def endpoint_token(self, entity_id: int, kind: str, topic: str, msgtype: str, qos: Qos) -> str:
        """Liveliness token of this node's publisher (``MP``) or subscription (``MS``)."""
        if kind not in (PUBLISHER, SUBSCRIPTION):
            raise CodecError(f"endpoint kind must be {PUBLISHER} or {SUBSCRIPTION}, got {kind!r}")
        return (f"{self._prefix(entity_id, kind)}/{mangle(check_topic(topic))}/"
                f"{dds_type_name(msgtype)}/{type_hash(msgtype)}/{qos.key()}")


def mangle(name: str) -> str:
    """``/`` -> ``%`` (a liveliness token chunk may not contain ``/``); empty -> ``%``."""
    return name.replace("/", "%") or "%"


def check_topic(topic: str) -> str:
    """Return ``topic`` if it is a fully qualified ROS 2 name (``/a/b_c``), else raise
    :class:`CodecError` (tokens: letters, digits, ``_``, not starting with a digit)."""
    tokens = topic.split("/")
    if not topic.startswith("/") or not all(_TOKEN_RE.match(t) for t in tokens[1:]):
        raise CodecError(f"{topic!r} is not a fully qualified ROS 2 topic name (/token/token...)")
    return topic


def ros_token(camera_id: str) -> str:
    """A camera id as one ROS name token: characters other than letters, digits and ``_``
    become ``_``, and a leading digit gets a ``cam_`` prefix (``fleet-a.1`` -> ``fleet_a_1``)."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", camera_id)
    return f"cam_{token}" if token[:1].isdigit() else token


def frame_ids(camera_id: str) -> tuple[str, str]:
    """``(world, camera)`` ``frame_id`` values of a camera's messages: ``<tok>/world`` (the SLAM
    world: the first camera pose's optical frame) and ``<tok>/camera_optical`` (x right, y down,
    z forward), ``<tok>`` = :func:`ros_token`."""
    tok = ros_token(camera_id)
    return f"{tok}/world", f"{tok}/camera_optical"


def parent_frame_id(camera_id: str, frame_id: str = "world") -> str:
    """The ROS ``header.frame_id`` of a camera's pose, path or cloud whose native ``frame_id``
    (:data:`~metricslam.wire.base.FrameId`) is ``frame_id``: ``map`` for ``"map"`` (the saved map
    the camera relocalized into, shared by every camera in it; metres), else the camera's own
    ``<tok>/world`` (:func:`frame_ids`). The one mapping the live ROS 2 bridge and the MCAP
    recordings share."""
    return "map" if frame_id == "map" else frame_ids(camera_id)[0]


def topic_key(domain_id: int, topic: str, msgtype: str, hash_chunk: str | None = None) -> str:
    """The data key expression of ``topic`` carrying ``msgtype``; ``hash_chunk`` replaces the
    type hash (``*`` for a subscriber that accepts every version of the type)."""
    if domain_id < 0:
        raise CodecError(f"ROS domain id must be >= 0, got {domain_id}")
    name = check_topic(topic).strip("/")
    return f"{domain_id}/{name}/{dds_type_name(msgtype)}/{hash_chunk or type_hash(msgtype)}"


def gid(token: str) -> bytes:
    """16-byte GID of the entity whose liveliness token is ``token``: the first 16 bytes of its
    SHA-256. The design document fixes only the size; rmw_zenoh itself hashes the same token
    (with XXH3-128), and subscribers treat the GID as an opaque, per-entity id."""
    return hashlib.sha256(token.encode()).digest()[:GID_BYTES]


def attachment(sequence_number: int, source_timestamp_ns: int, publisher_gid: bytes) -> bytes:
    """The 33-byte attachment of one published sample (module docstring)."""
    if len(publisher_gid) != GID_BYTES:
        raise CodecError(f"a GID has {GID_BYTES} bytes, got {len(publisher_gid)}")
    return _ATTACHMENT.pack(sequence_number, source_timestamp_ns, GID_BYTES) + bytes(publisher_gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """``(sequence_number, source_timestamp_ns, gid)`` of an rmw_zenoh sample attachment."""
    if len(data) != _ATTACHMENT.size + GID_BYTES:
        raise CodecError(f"rmw_zenoh attachment has {_ATTACHMENT.size + GID_BYTES} bytes, got {len(data)}")
    seq, t_ns, n = _ATTACHMENT.unpack_from(data, 0)
    if n != GID_BYTES:
        raise CodecError(f"attachment GID length byte is {n}, expected {GID_BYTES}")
    return seq, t_ns, bytes(data[_ATTACHMENT.size:])
