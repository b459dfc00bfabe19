"""Zenoh key expressions of the SLAM stack (pure strings; no zenoh import).

Per camera ``<camera_id>``::

    metricslam/<camera_id>/frame        in   FrameMessage (image + intrinsics)
    metricslam/<camera_id>/calibration  in   CalibrationMessage (optional; frames carry it too)
    metricslam/<camera_id>/pose         out  PoseMessage, one per input frame
    metricslam/<camera_id>/odom         out  OdometryMessage, one per input frame: the continuous
                                             pose (corrections blended in; never jumps)
    metricslam/<camera_id>/keyframe     out  KeyframeMessage, one per new keyframe
    metricslam/<camera_id>/status       out  StatusMessage, periodically
    metricslam/<camera_id>/trajectory   queryable -> TrajectoryMessage (whole current trajectory)
    metricslam/<camera_id>/path         out  TrajectoryMessage, whenever the optimized trajectory
                                             changed (a new keyframe or a global solve)
    metricslam/<camera_id>/landmarks    out  LandmarksMessage, the local window's after a keyframe
    metricslam/<camera_id>/keyframe_depth out KeyframeDepthMessage, each answered depth request
    metricslam/_service/health          queryable -> JSON of the SLAM service's readiness
    metricslam/_router/health           queryable -> JSON, answered by the router of ``metricslam up``
                                             itself (the supervisor's liveness probe)
    metricslam/_service/map/save/<camera_id>  queryable -> JSON: the camera's session map saved to
                                             the folder the payload names (docs/maps.md)

Camera ids are one key chunk: letters, digits, ``-``, ``_`` and ``.``; they may not start with
``_`` (reserved for service keys).
"""

from __future__ import annotations

import re

from metricslam.errors import CodecError

PREFIX = "metricslam"
HEALTH_KEY = f"{PREFIX}/_service/health"
ROUTER_HEALTH_KEY = f"{PREFIX}/_router/health"
_CAMERA_ID_RE = re.compile(r"^[A-Za-z0-9.\-][A-Za-z0-9_.\-]{0,63}$")
TOPICS = ("frame", "calibration", "pose", "keyframe", "status", "trajectory", "path", "landmarks",
          "keyframe_depth", "odom")


def check_camera_id(camera_id: str) -> str:
    """Return ``camera_id`` if it is a valid single key chunk, else raise :class:`CodecError`."""
    if not isinstance(camera_id, str) or not _CAMERA_ID_RE.match(camera_id):
        raise CodecError(
            f"invalid camera id {camera_id!r}: use 1-64 letters, digits, '-', '_' or '.', "
            "not starting with '_'"
        )
    return camera_id


def key(camera_id: str, topic: str) -> str:
    """``metricslam/<camera_id>/<topic>`` for one of :data:`TOPICS`."""
    if topic not in TOPICS:
        raise CodecError(f"unknown topic {topic!r}; expected one of {TOPICS}")
    return f"{PREFIX}/{check_camera_id(camera_id)}/{topic}"


def wildcard(topic: str) -> str:
    """``metricslam/*/<topic>``: every camera's ``topic``."""
    if topic not in TOPICS:
        raise CodecError(f"unknown topic {topic!r}; expected one of {TOPICS}")
    return f"{PREFIX}/*/{topic}"


def parse_key(key_expr: str) -> tuple[str, str]:
    """``metricslam/<camera_id>/<topic>`` -> ``(camera_id, topic)``; raises :class:`CodecError`."""
    parts = str(key_expr).split("/")
    if len(parts) != 3 or parts[0] != PREFIX or parts[2] not in TOPICS:
        raise CodecError(f"key {key_expr!r} is not of the form {PREFIX}/<camera_id>/<topic>")
    return check_camera_id(parts[1]), parts[2]


#: the SLAM service's queryable ``metricslam/_service/reset/<camera_id>``: the camera's next
#: frame starts a fresh session, not continuing its earlier trajectory (docs/usage.md)
RESET_KEY_PREFIX = f"{PREFIX}/_service/reset"


def reset_key(camera_id: str) -> str:
    """``metricslam/_service/reset/<camera_id>`` (:data:`RESET_KEY_PREFIX`)."""
    return f"{RESET_KEY_PREFIX}/{check_camera_id(camera_id)}"


#: the SLAM service's queryable ``metricslam/_service/finish/<camera_id>``: close the camera now
#: (window marginalized, final solve), its final trajectory kept on ``…/trajectory`` (docs/usage.md)
FINISH_KEY_PREFIX = f"{PREFIX}/_service/finish"


def finish_key(camera_id: str) -> str:
    """``metricslam/_service/finish/<camera_id>`` (:data:`FINISH_KEY_PREFIX`)."""
    return f"{FINISH_KEY_PREFIX}/{check_camera_id(camera_id)}"


#: the SLAM service's queryable ``metricslam/_service/map/save/<camera_id>``: save the camera's
#: session map to the folder named by the query's payload (docs/maps.md)
MAP_SAVE_KEY_PREFIX = f"{PREFIX}/_service/map/save"


def map_save_key(camera_id: str) -> str:
    """``metricslam/_service/map/save/<camera_id>`` (:data:`MAP_SAVE_KEY_PREFIX`)."""
    return f"{MAP_SAVE_KEY_PREFIX}/{check_camera_id(camera_id)}"
