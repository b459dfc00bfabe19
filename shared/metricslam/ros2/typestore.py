"""ROS 2 message types, their REP-2016 type hashes and CDR (de)serialization, via ``rosbags``.

The type definitions are those of ROS 2 Jazzy as ``rosbags.typesys.Stores.ROS2_JAZZY`` ships
them (the messages used here are identical in Humble, Jazzy and Rolling). ``rosbags`` is the
``ros`` extra and is imported on first use, so importing this module costs nothing.

Example::

    >>> type_hash("std_msgs/msg/String")   # the value rmw_zenoh's design document shows
    'RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18'
    >>> dds_type_name("nav_msgs/msg/Odometry")
    'nav_msgs::msg::dds_::Odometry_'
"""

from __future__ import annotations

import functools
from typing import Any

from metricslam.errors import CodecError, ConfigError

#: message types this project publishes or reads (``pkg/msg/Name``)
ODOMETRY = "nav_msgs/msg/Odometry"
PATH = "nav_msgs/msg/Path"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
FLOAT64 = "std_msgs/msg/Float64"
BOOL = "std_msgs/msg/Bool"


@functools.cache
def typestore() -> Any:
    """The ``rosbags`` type store of ROS 2 Jazzy (cached).

    Raises:
        ConfigError: ``rosbags`` is not installed.
    """
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise ConfigError("ROS 2 messages need rosbags: pip install 'metricslam[ros]'") from None
    return get_typestore(Stores.ROS2_JAZZY)


def msg_class(msgtype: str) -> type:
    """The dataclass of ``msgtype`` (``pkg/msg/Name``)."""
    try:
        return typestore().types[msgtype]
    except KeyError:
        raise CodecError(f"unknown ROS 2 message type {msgtype!r}") from None


@functools.cache
def type_hash(msgtype: str) -> str:
    """``RIHS01_<sha256 hex>`` of ``msgtype``: REP-2016's hash of the type description JSON
    (the type, its fields' type ids, and every type it references), as rosidl generates it."""
    msg_class(msgtype)
    return typestore().hash_rihs01(msgtype)


def dds_type_name(msgtype: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``: the type name rmw implementations put in
    key expressions and liveliness tokens for CDR-encoded messages."""
    parts = msgtype.split("/")
    if len(parts) != 3 or parts[1] not in ("msg", "srv") or not all(parts):
        raise CodecError(f"ROS 2 type {msgtype!r} is not of the form pkg/msg/Name")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


@functools.cache
def msgdef(msgtype: str) -> str:
    """The ``ros2msg`` schema text of ``msgtype``: its ``.msg`` definition followed by every
    referenced type's, each after a ``====…`` line and ``MSG: pkg/Name`` (what MCAP readers and
    Foxglove expect for ``schema_encoding=ros2msg``)."""
    msg_class(msgtype)
    return typestore().generate_msgdef(msgtype, ros_version=2)[0]


def serialize(message: Any) -> bytes:
    """CDR (little-endian, with the 4-byte encapsulation header) of a ``rosbags`` message."""
    return bytes(typestore().serialize_cdr(message, message.__msgtype__))


def deserialize(payload: bytes | bytearray | memoryview, msgtype: str) -> Any:
    """Parse CDR bytes as ``msgtype``.

    Raises:
        CodecError: the bytes are not a valid ``msgtype`` (truncated, wrong type, ...).
    """
    msg_class(msgtype)
    try:
        return typestore().deserialize_cdr(bytes(payload), msgtype)
    except Exception as exc:  # rosbags raises struct/index/assertion errors on bad input
        raise CodecError(f"not a valid CDR {msgtype}: {type(exc).__name__}: {exc}") from None
