"""Wire messages of the SLAM stack (Zenoh payloads) and their key expressions.

Pure: importing this never imports zenoh. ``codec`` owns encoding; ``keys`` owns key expressions;
``base`` holds :class:`Message`, which the message modules (``camera_messages``, ``map_messages``,
``odometry_message``) build on. Imports run one way, messages -> ``base`` -> ``keys``, and ``codec``
on top (``tests/test_wire_import_graph.py``).
"""

from metricslam.wire.codec import (
    CalibrationMessage,
    FrameMessage,
    KeyframeMessage,
    Message,
    PoseMessage,
    StatusMessage,
    TrajectoryMessage,
    decode,
    decode_as,
    encode,
)
from metricslam.wire.map_messages import KeyframeDepthMessage, LandmarksMessage
from metricslam.wire.odometry_message import OdometryMessage

__all__ = [
    "CalibrationMessage", "FrameMessage", "KeyframeDepthMessage", "KeyframeMessage", "LandmarksMessage",
    "Message", "OdometryMessage", "PoseMessage",
    "StatusMessage", "TrajectoryMessage", "decode", "decode_as", "encode",
]
