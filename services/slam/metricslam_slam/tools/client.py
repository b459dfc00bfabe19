"""Client-side helpers over a zenoh session: publish frames, record poses/status, query.

Used by the ``replay``/``poses``/``camera``/``demo`` commands, the benchmark and the tests.
"""

from __future__ import annotations

import json
import threading
import time
from typing import Callable

import numpy as np
import zenoh

from metricslam.camera import PinholeCamera
from metricslam.errors import CodecError, ServiceError
from metricslam.wire import keys
from metricslam.wire.codec import (
    FrameMessage, KeyframeMessage, PoseMessage, StatusMessage, TrajectoryMessage, decode_as, encode,
)
from metricslam.wire.map_messages import KeyframeDepthMessage, LandmarksMessage

#: how the detail of a ``session_restarted`` status starts when the service did NOT continue the
#: camera's earlier trajectory (the same text as ``camera_worker.NEW_SESSION``, which the tools
#: may not import; a test checks they agree)
NEW_SESSION = "new session"


def new_sessions(statuses: list[StatusMessage]) -> list[str]:
    """Details of the ``session_restarted`` statuses that started a fresh session (nothing
    continued: frames went backwards, or a reset)."""
    return [s.event_detail or "" for s in statuses
            if s.event == "session_restarted" and (s.event_detail or "").startswith(NEW_SESSION)]


def continued_sessions(statuses: list[StatusMessage]) -> list[str]:
    """Details of the ``session_restarted`` statuses that continued the camera's earlier
    trajectory: the service restarted (or the camera came back after an idle close)."""
    return [s.event_detail or "" for s in statuses
            if s.event == "session_restarted" and not (s.event_detail or "").startswith(NEW_SESSION)]


def service_restart(before: dict | None, after: dict | None, statuses: list[StatusMessage]) -> str | None:
    """Why the SLAM service looks restarted between two health answers (``instance`` changed, or
    no answer now) or from a continuing ``session_restarted`` status; None if it does not."""
    if before is not None and after is not None and before.get("instance") != after.get("instance"):
        return "it answers as a new instance, started " + time.strftime(
            "%H:%M:%S", time.localtime(int(after.get("started_t_ns") or 0) / 1e9))
    continued = continued_sessions(statuses)
    if continued:
        return f"session_restarted: {continued[-1]}"
    if before is not None and after is None:
        return "no SLAM service answers its health query now: it is down or restarting"
    return None


def describe_counters(status: StatusMessage) -> str:
    """The frame counters of a camera's ``…/status`` in words (counted since its session started)."""
    return (f"{status.frames_received} received, {status.frames_processed} processed, "
            f"{status.queue_drops} dropped from a full queue, {status.malformed} malformed")


class FramePublisher:
    """Publishes one camera's frames. ``block=True`` (replay) never drops in the transport;
    ``block=False`` (live camera) lets zenoh drop under congestion."""

    def __init__(self, session: zenoh.Session, camera_id: str, block: bool = True) -> None:
        self.camera_id = keys.check_camera_id(camera_id)
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self._publisher = session.declare_publisher(keys.key(camera_id, "frame"), congestion_control=cc)

    def wait_for_subscriber(self, timeout_s: float) -> bool:
        """Wait until zenoh knows a subscriber of this camera's frames (a SLAM service).

        A publisher declared just now drops its puts until the router has told it of a matching
        subscriber, which takes milliseconds on an idle machine and seconds on a loaded one.
        Returns False if none is known after ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while not self._publisher.matching_status.matching:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def publish(self, frame_index: int, t_ns: int, image: np.ndarray, camera: PinholeCamera) -> int:
        """Send one frame; returns the send time (``time.perf_counter_ns``) for latency bookkeeping."""
        message = FrameMessage(camera_id=self.camera_id, frame_index=frame_index, t_ns=t_ns,
                               camera=camera, t_sent_ns=time.time_ns(), image=image)
        payload = encode(message)
        t_send = time.perf_counter_ns()
        self._publisher.put(payload)
        return t_send

    def close(self) -> None:
        self._publisher.undeclare()


class PoseRecorder:
    """Records ``…/pose`` (and ``…/status``, ``…/keyframe``) of one camera as they arrive.

    Attributes:
        poses: frame_index -> the latest :class:`PoseMessage` for it.
        arrival_ns: frame_index -> ``time.perf_counter_ns()`` at arrival.
        statuses: every :class:`StatusMessage` received, in order.
        keyframes: every :class:`KeyframeMessage` received.
        paths, landmarks, depths: with ``map_topics``, every ``…/path`` (TrajectoryMessage),
            ``…/landmarks`` and ``…/keyframe_depth`` message received, in arrival order.
        malformed: payloads that did not decode.
    """

    def __init__(self, session: zenoh.Session, camera_id: str, map_topics: bool = False) -> None:
        self.camera_id = keys.check_camera_id(camera_id)
        self.poses: dict[int, PoseMessage] = {}
        self.arrival_ns: dict[int, int] = {}
        self.statuses: list[StatusMessage] = []
        self.keyframes: list[KeyframeMessage] = []
        self.paths: list[TrajectoryMessage] = []
        self.landmarks: list[LandmarksMessage] = []
        self.depths: list[KeyframeDepthMessage] = []
        self.malformed = 0
        self._cond = threading.Condition()
        self._subs = [
            session.declare_subscriber(keys.key(camera_id, "pose"), self._on_pose),
            session.declare_subscriber(keys.key(camera_id, "status"), self._on_status),
            session.declare_subscriber(keys.key(camera_id, "keyframe"), self._on_keyframe),
        ]
        if map_topics:
            for topic, cls, into in (("path", TrajectoryMessage, self.paths),
                                     ("landmarks", LandmarksMessage, self.landmarks),
                                     ("keyframe_depth", KeyframeDepthMessage, self.depths)):
                self._subs.append(session.declare_subscriber(
                    keys.key(camera_id, topic), lambda sample, c=cls, i=into: self._append(sample, c, i)))

    def _append(self, sample: zenoh.Sample, cls, into: list) -> None:
        msg = self._decode(sample, cls)
        if msg is not None:
            with self._cond:
                into.append(msg)

    def _decode(self, sample: zenoh.Sample, cls):
        try:
            return decode_as(sample.payload.to_bytes(), cls)
        except CodecError:
            self.malformed += 1
            return None

    def _on_pose(self, sample: zenoh.Sample) -> None:
        t = time.perf_counter_ns()
        msg = self._decode(sample, PoseMessage)
        if msg is not None:
            with self._cond:
                self.poses[msg.frame_index] = msg
                self.arrival_ns[msg.frame_index] = t
                self._cond.notify_all()

    def _on_status(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample, StatusMessage)
        if msg is not None:
            with self._cond:
                self.statuses.append(msg)
                self._cond.notify_all()

    def _on_keyframe(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample, KeyframeMessage)
        if msg is not None:
            with self._cond:
                self.keyframes.append(msg)

    def wait_for(self, predicate, timeout_s: float) -> bool:
        """Wait until ``predicate(self)`` is true (re-checked on every arrival) or the timeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not predicate(self):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.5))
        return True

    def wait_frames(self, n_frames: int, timeout_s: float) -> bool:
        """Wait until poses of ``n_frames`` distinct frames arrived."""
        return self.wait_for(lambda r: len(r.poses) >= n_frames, timeout_s)

    def received_frames(self) -> set[int]:
        """Frame indices whose pose arrived so far."""
        with self._cond:
            return set(self.poses)

    def statuses_so_far(self) -> list[StatusMessage]:
        """A copy of :attr:`statuses` (they keep arriving on zenoh's thread)."""
        with self._cond:
            return list(self.statuses)

    def latest_status(self) -> StatusMessage | None:
        with self._cond:
            return self.statuses[-1] if self.statuses else None

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


def query_trajectory(session: zenoh.Session, camera_id: str, timeout_s: float = 5.0) -> TrajectoryMessage:
    """Ask the SLAM service for a camera's whole current trajectory."""
    errors = []
    for reply in session.get(keys.key(camera_id, "trajectory"), timeout=timeout_s):
        if reply.ok is not None:
            return decode_as(reply.ok.payload.to_bytes(), TrajectoryMessage)
        errors.append(reply.err.payload.to_bytes().decode(errors="replace"))
    raise ServiceError(f"no trajectory for camera {camera_id!r}: {'; '.join(errors) or 'no SLAM service answered'}")


def settled_trajectory(query: Callable[[], TrajectoryMessage], timeout_s: float = 10.0,
                       period_s: float = 0.5, agreeing: int = 3) -> TrajectoryMessage:
    """The optimized trajectory once ``agreeing`` answers ``period_s`` apart are the same (the
    last keyframes' depth answers, loops and solves land after the last pose), or the latest
    answer after ``timeout_s``.

    Args:
        query: one ask, e.g. ``lambda: query_trajectory(session, "cam0")``.
    """
    last = query()
    same = 1
    deadline = time.monotonic() + timeout_s
    while same < agreeing and time.monotonic() < deadline:
        time.sleep(period_s)
        now = query()
        unchanged = (np.array_equal(now.frame_index, last.frame_index)
                     and np.array_equal(now.T_world_cam, last.T_world_cam))
        same = same + 1 if unchanged else 1
        last = now
    return last


def reset_camera(session: zenoh.Session, camera_id: str, why: str = "", timeout_s: float = 5.0) -> dict:
    """Ask the SLAM service to start a fresh session at ``camera_id``'s next frame (its earlier
    trajectory is not continued); returns its answer ``{"camera_id", "earlier_poses", "instance"}``.

    Raises:
        ServiceError: no SLAM service serving the camera answered.
    """
    return _camera_command(session, keys.reset_key(camera_id), f"reset camera {camera_id!r}", why, timeout_s)


def finish_camera(session: zenoh.Session, camera_id: str, why: str = "", timeout_s: float = 60.0) -> dict:
    """Ask the SLAM service to close ``camera_id`` now (its local window marginalized, the final
    solve run: the final trajectory, as ``metricslam run`` writes it at the end), answered once
    done: ``{"camera_id", "finished", "instance"}`` (``finished`` False: no running session).

    Raises:
        ServiceError: no SLAM service serving the camera answered.
    """
    return _camera_command(session, keys.finish_key(camera_id), f"finish camera {camera_id!r}", why, timeout_s)


def _camera_command(session: zenoh.Session, key: str, what: str, why: str, timeout_s: float) -> dict:
    errors = []
    for reply in session.get(key, payload=why.encode(), timeout=timeout_s):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
        errors.append(reply.err.payload.to_bytes().decode(errors="replace"))
    raise ServiceError(f"could not {what}: "
                       f"{'; '.join(errors) or 'no SLAM service serving it answered'}; is one running (`metricslam up`)?")


def query_health(session: zenoh.Session, timeout_s: float = 2.0) -> dict | None:
    """The SLAM service's health JSON, or None if no service answered in time."""
    for reply in session.get(keys.HEALTH_KEY, timeout=timeout_s):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None
