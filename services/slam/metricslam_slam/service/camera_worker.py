"""One camera's worker: bounded drop-oldest frame queue -> SlamSession -> pose/keyframe out.

The zenoh callback only calls :meth:`CameraWorker.offer` (append raw bytes, O(1)); decoding and
SLAM run on the worker's own thread so a slow frame never blocks the transport. Malformed frames
(bad bytes, wrong camera id, intrinsics that change mid-stream) are counted and dropped.

A camera's trajectory is continued only while its frames go on. A frame whose index or timestamp
goes backwards (:func:`~metricslam_slam.service.continued_session.why_new_session`: a second
replay, another sequence, a restarted camera), or the first frame after a reset request
(:meth:`CameraWorker.request_new_session`), starts a fresh session at the origin: the earlier
poses are forgotten (``forget_prior``), a warning is logged and a ``session_restarted`` status
whose detail starts with :data:`NEW_SESSION` says why. Such a frame may also bring new
intrinsics (another camera under the same id).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Callable

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.datasets.base import Frame
from metricslam.errors import CodecError
from metricslam.slam.types import PoseEstimate, ScaleState, SlamSession, TrackingState
from metricslam.wire.codec import FrameMessage, KeyframeMessage, Message, PoseMessage, StatusMessage, decode_as
from metricslam_slam.service.continued_session import ContinuedSession, why_new_session
from metricslam_slam.service.memory import release_memory
from metricslam_slam.service.odometry_stream import OdometryStream
from metricslam_slam.service.scale_health import scale_health_status

log = logging.getLogger(__name__)
Publish = Callable[[str, Message], None]  # (topic, message)
#: how the detail of a ``session_restarted`` status starts when the camera's earlier trajectory
#: is NOT continued (a fresh session at the origin); a continuing one starts "continuing from"
NEW_SESSION = "new session"


class CameraWorker:
    """Owns one camera's queue, session and counters.

    Args:
        camera_id: the key chunk of ``metricslam/<camera_id>/frame``.
        session_factory: ``(camera_id, camera) -> SlamSession``, called on the first valid frame.
        publish: sends a message on ``metricslam/<camera_id>/<topic>``.
        queue_size: frames held (``SystemConfig.queues.frames``); on overflow the oldest is
            dropped and counted.
        keyframe_images: attach the image to keyframe messages.
        on_estimate: called after each processed frame (the optional live viewer).
        prior_poses: the camera's earlier poses, asked for on the first valid frame; when there
            are some, the session continues them (:class:`ContinuedSession`, event
            ``session_restarted``).
        on_session: called with each new session (the service attaches the map publisher).
        on_event: ``(event, detail)`` of the camera's session (``StatusMessage.event``).
        max_session_keyframes: after this many keyframes the session is closed and a new one
            continues it (``session_rolled_over``), which bounds its memory; None: never.
        forget_prior: called when a fresh session replaces the camera's earlier trajectory
            (frames went backwards, or a reset): the earlier poses must not be continued later
            (the service moves its persisted file aside).
    """

    def __init__(self, camera_id: str, session_factory: Callable[[str, PinholeCamera], SlamSession],
                 publish: Publish, queue_size: int, keyframe_images: bool = False,
                 on_estimate: Callable[[str, Frame, PoseEstimate, SlamSession], None] | None = None,
                 prior_poses: Callable[[], list[PoseEstimate]] | None = None,
                 on_session: Callable[[SlamSession], None] | None = None,
                 on_event: Callable[[str, str], None] | None = None,
                 max_session_keyframes: int | None = None,
                 forget_prior: Callable[[], None] | None = None) -> None:
        self.camera_id = camera_id
        self._factory = session_factory
        self._prior_poses = prior_poses
        self._on_session = on_session
        self._on_event = on_event
        self._max_session_keyframes = max_session_keyframes
        self._session_keyframes = 0
        self._forget_prior = forget_prior
        self._new_session_reason: str | None = None  # set by request_new_session, used by the next frame
        self._last_frame: tuple[int, int] | None = None  # (frame_index, t_ns) of the last frame processed
        self._final: list[PoseEstimate] = []  # the trajectory at close, once the session is freed
        self.last_frame_s = time.monotonic()  # when the latest frame was offered (idle close)
        self._publish = publish
        self._keyframe_images = keyframe_images
        self._on_estimate = on_estimate
        self._queue: collections.deque[tuple[int, bytes]] = collections.deque(maxlen=queue_size)
        self._cond = threading.Condition()
        self._stop = False
        self._busy_since_s: float | None = None  # monotonic start of the frame being handled (watchdog)
        self._session: SlamSession | None = None
        self._session_lock = threading.Lock()
        self._camera: PinholeCamera | None = None
        self.frames_received = 0
        self.frames_processed = 0
        self.queue_drops = 0
        self.malformed = 0
        self.keyframes = 0
        self.last_state: TrackingState | None = None
        self.scale_established = False
        self.scale_state: ScaleState | None = None
        self._latencies_ms: collections.deque[float] = collections.deque(maxlen=500)
        self._done_times: collections.deque[float] = collections.deque(maxlen=50)
        self._last_T = np.eye(4)
        self._vo_suspect = False  # the latest pose's VO tracks may be aliased (one event per run)
        self._frame_id = "world"  # of the last published pose ("map": relocalized into the service's map)
        self._odometry = OdometryStream(camera_id, publish)  # ".../odom", beside ".../pose"
        self._thread = threading.Thread(target=self._run, name=f"slam-{camera_id}", daemon=True)
        self._thread.start()

    # -- called from zenoh's thread ----------------------------------------------------------
    def offer(self, payload: bytes) -> bool:
        """Queue a raw frame payload; drops (and counts) the oldest when full. False (nothing
        queued) once :meth:`close` was called."""
        with self._cond:
            if self._stop:
                return False
            self.last_frame_s = time.monotonic()
            self.frames_received += 1
            if len(self._queue) == self._queue.maxlen:
                self.queue_drops += 1
            self._queue.append((time.perf_counter_ns(), payload))
            self._cond.notify()
            return True

    def request_new_session(self, reason: str) -> None:
        """Start a fresh session (not continuing anything) at the next frame, saying ``reason``."""
        with self._cond:
            self._new_session_reason = reason

    # -- worker thread -----------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._stop:
                    self._cond.wait()
                if self._stop and not self._queue:
                    return
                t_in_ns, payload = self._queue.popleft()
            self._busy_since_s = time.monotonic()
            try:
                self._handle(t_in_ns, payload)
            except Exception:  # a bad frame or a session bug must never end the loop
                log.exception("camera %s: frame handling failed", self.camera_id)
            finally:
                self._busy_since_s = None

    @property
    def camera(self) -> PinholeCamera | None:
        """The intrinsics of the camera's frames (None before its first valid frame)."""
        return self._camera

    @property
    def frame_id(self) -> str:
        """The frame the session's poses are in now: ``"map"`` once it relocalized into the
        service's saved map (:class:`~metricslam.slam.map.localization.MapFrameSession`)."""
        return getattr(self._session, "frame_id", "world")

    def with_session(self, fn: Callable[[SlamSession], object]) -> object:
        """``fn(session)`` between two frames (under the session lock); None without a session."""
        with self._session_lock:
            return None if self._session is None else fn(self._session)

    def stalled_s(self, now_s: float) -> float:
        """Seconds (monotonic) the worker has been on its current frame; 0 while waiting for one
        (the service's watchdog, :mod:`metricslam_slam.service.watchdog`)."""
        since = self._busy_since_s
        return 0.0 if since is None else now_s - since

    def _reject(self, why: str) -> None:
        self.malformed += 1
        if self.malformed <= 5 or self.malformed % 100 == 0:
            log.warning("camera %s: dropped malformed frame #%d: %s", self.camera_id, self.malformed, why)

    def _handle(self, t_in_ns: int, payload: bytes) -> None:
        try:
            msg = decode_as(payload, FrameMessage)
        except CodecError as exc:
            return self._reject(str(exc))
        if msg.camera_id != self.camera_id:
            return self._reject(f"header camera_id {msg.camera_id!r} != key camera id")
        with self._cond:
            reason, self._new_session_reason = self._new_session_reason, None
        if self._camera is None:
            self._first_session(msg, reason)
        else:
            if reason is None and self._last_frame is not None:
                reason = why_new_session(*self._last_frame, msg.frame_index, msg.t_ns)
            if reason is not None:
                self._fresh_session(msg.camera, reason)
            elif msg.camera != self._camera:
                return self._reject("intrinsics changed mid-stream; use a new camera id, or reset this one "
                                    "(`metricslam replay --new-session`, docs/usage.md)")
        self._last_frame = (msg.frame_index, msg.t_ns)
        frame = Frame(index=msg.frame_index, t_ns=msg.t_ns, image=msg.image, camera=msg.camera)
        with self._session_lock:
            try:
                est = self._session.process(frame)
            except Exception:  # the protocol says process never raises; be defensive anyway
                log.exception("camera %s: session.process raised", self.camera_id)
                est = PoseEstimate(msg.frame_index, msg.t_ns, self._last_T, TrackingState.INVALID_FRAME)
        self._last_T = est.T_world_cam
        if est.vo_suspect and not self._vo_suspect:  # a run of suspect frames starts
            self._event("vo_suspect", f"frame {est.frame_index}: the VO's tracks may be aliased on repeating "
                        "texture; its poses from here may be wrong (docs/vo.md, 'Aliased tracks')")
        self._vo_suspect = est.vo_suspect
        latency_ms = (time.perf_counter_ns() - t_in_ns) / 1e6
        frame_id = self.frame_id
        if frame_id != self._frame_id:  # relocalized into the map: the continuous stream starts over there
            self._frame_id = frame_id
            self._odometry = OdometryStream(self.camera_id, self._publish)
            self._odometry.attach(self._session)
        self._publish("pose", PoseMessage(
            camera_id=self.camera_id, frame_index=est.frame_index, t_ns=est.t_ns,
            state=est.state, is_keyframe=est.is_keyframe, segment_id=est.segment_id,
            scale_established=est.scale_established, processing_ms=latency_ms,
            t_sent_ns=msg.t_sent_ns, scale_state=est.scale_state, scale_factors=est.scale_factors,
            frame_id=frame_id, T_world_cam=np.asarray(est.T_world_cam, dtype=np.float64)))
        self._odometry.after_pose(est, frame_id)
        if est.is_keyframe:
            self.keyframes += 1
            self._session_keyframes += 1
            self._publish("keyframe", KeyframeMessage(
                camera_id=self.camera_id, frame_index=est.frame_index, t_ns=est.t_ns,
                segment_id=est.segment_id, scale_established=est.scale_established, frame_id=frame_id,
                T_world_cam=np.asarray(est.T_world_cam, dtype=np.float64),
                image=msg.image if self._keyframe_images else None))
        if self._on_estimate is not None:
            self._on_estimate(self.camera_id, frame, est, self._session)
        self.frames_processed += 1
        self.last_state = est.state
        self.scale_established = est.scale_established
        self.scale_state = est.scale_state
        self._latencies_ms.append(latency_ms)
        self._done_times.append(time.monotonic())
        if self._max_session_keyframes is not None and self._session_keyframes >= self._max_session_keyframes:
            self._roll_over()

    def _first_session(self, msg: FrameMessage, reason: str | None) -> None:
        """The worker's first session: continues the camera's earlier poses unless ``reason`` (a
        reset) or the frame goes backwards from them."""
        prior = [] if reason is not None or self._prior_poses is None else self._prior_poses()
        if prior:
            last = prior[-1]
            reason = why_new_session(last.frame_index, last.t_ns, msg.frame_index, msg.t_ns)
        if reason is not None:
            self._forget()
        with self._session_lock:
            self._session = self._start_session(msg.camera, [] if reason is not None else prior)
        self._camera = msg.camera
        log.info("camera %s: new SLAM session, %s", self.camera_id, msg.camera)
        if reason is not None:
            self._announce_new_session(reason, prior)
        elif prior:
            self._event("session_restarted", f"continuing from frame {prior[-1].frame_index} "
                        f"({len(prior)} earlier poses) as segment "
                        f"{getattr(self._session, 'first_segment_id', 0)}")

    def _fresh_session(self, camera: PinholeCamera, reason: str) -> None:
        """Replace the running session by a fresh one at the origin (nothing continued)."""
        def fresh(earlier: list[PoseEstimate]) -> SlamSession:
            self._forget()
            # a new trajectory, not a correction of the old one: the continuous stream starts over
            # at the origin instead of blending back to it
            self._odometry = OdometryStream(self.camera_id, self._publish)
            self._camera = camera
            return self._start_session(camera, [])

        earlier = self._replace_session(fresh, "start a new one")
        self._announce_new_session(reason, earlier)

    def _replace_session(self, start: Callable[[list[PoseEstimate]], SlamSession], why: str) -> list[PoseEstimate]:
        """Close the running session, start ``start(its final trajectory)`` in its place under the
        session lock, free the old one's memory; returns that final trajectory."""
        with self._session_lock:
            old = self._session
            try:
                old.close()
            except Exception:  # noqa: BLE001 -- the camera goes on in a new session regardless
                log.exception("camera %s: closing the session to %s failed", self.camera_id, why)
            earlier = old.trajectory()
            self._session = start(earlier)
        del old
        release_memory()
        return earlier

    def _forget(self) -> None:
        if self._forget_prior is not None:
            try:
                self._forget_prior()
            except Exception:  # noqa: BLE001 -- the new session starts regardless
                log.exception("camera %s: forgetting the earlier trajectory failed", self.camera_id)

    def _announce_new_session(self, reason: str, earlier: list[PoseEstimate]) -> None:
        what = (f"its earlier trajectory ({len(earlier)} poses, to frame {earlier[-1].frame_index}) is not "
                "continued" if earlier else "nothing earlier is continued")
        detail = f"{NEW_SESSION} at the origin: {reason}; {what}"
        log.warning("camera %s: %s", self.camera_id, detail)
        self._event("session_restarted", detail)

    def _start_session(self, camera: PinholeCamera, prior: list[PoseEstimate]) -> SlamSession:
        session = self._factory(self.camera_id, camera)
        if prior:
            session = ContinuedSession(session, prior)
        self._session_keyframes = 0
        self._odometry.attach(session)
        if self._on_session is not None:
            self._on_session(session)
        return session

    def _roll_over(self) -> None:
        """Close the session (its final trajectory is kept) and continue in a new one."""
        prior = self._replace_session(lambda earlier: self._start_session(self._camera, earlier), "roll over")
        self._event("session_rolled_over", f"{self._max_session_keyframes} keyframes in one session; continuing "
                    f"from frame {prior[-1].frame_index if prior else '-'} as segment "
                    f"{getattr(self._session, 'first_segment_id', 0)}")

    def _event(self, event: str, detail: str) -> None:
        if self._on_event is not None:
            try:
                self._on_event(event, detail)
            except Exception:  # noqa: BLE001 -- an event is best effort
                log.exception("camera %s: publishing %s failed", self.camera_id, event)

    def idle_s(self, now_s: float) -> float:
        """Seconds since the latest frame was offered (0 while frames are queued)."""
        with self._cond:
            return 0.0 if self._queue else now_s - self.last_frame_s

    # -- queries -----------------------------------------------------------------------------
    def trajectory(self) -> list[PoseEstimate]:
        """The session's current trajectory (waits for at most the frame being processed)."""
        with self._session_lock:
            return list(self._final) if self._session is None else list(self._session.trajectory())

    def framed_trajectory(self) -> tuple[str, list[PoseEstimate]]:
        """``(frame_id, trajectory)`` read together: a session relocalizes between two frames."""
        with self._session_lock:
            if self._session is None:
                return self._frame_id, list(self._final)
            return getattr(self._session, "frame_id", "world"), list(self._session.trajectory())

    def status(self, depth_url: str | None, depth_reachable: bool | None,
               depth_error: str | None, depth_outages: int = 0) -> StatusMessage:
        """This camera's :class:`StatusMessage`; the ``depth_*`` fields describe the service's
        link to its depth service (``depth_outages``: times it became unreachable)."""
        lat = np.array(self._latencies_ms) if self._latencies_ms else None
        times = list(self._done_times)
        fps = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 and times[-1] > times[0] else 0.0
        stats: dict = {}
        scale_health = None
        if self._session is not None:
            try:
                raw = self._session.stats()
                stats, scale_health = _flatten(raw), scale_health_status(raw)
            except Exception:  # stats are best effort
                log.exception("camera %s: session.stats failed", self.camera_id)
        return StatusMessage(
            camera_id=self.camera_id, t_ns=time.time_ns(), frames_received=self.frames_received,
            frames_processed=self.frames_processed, queue_drops=self.queue_drops,
            malformed=self.malformed, queue_depth=len(self._queue), fps=fps,
            latency_ms_p50=None if lat is None else float(np.percentile(lat, 50)),
            latency_ms_p99=None if lat is None else float(np.percentile(lat, 99)),
            tracking_state=self.last_state, scale_established=self.scale_established,
            keyframes=self.keyframes, depth_url=depth_url, depth_reachable=depth_reachable,
            depth_error=depth_error, depth_outages=depth_outages, scale_state=self.scale_state,
            session_stats=stats, scale_health=scale_health)

    def close(self, timeout_s: float = 10.0) -> None:
        """Finish the queued frames, stop the thread, close and free the session (its final
        trajectory stays available from :meth:`trajectory`)."""
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(timeout_s)
        with self._session_lock:
            if self._session is not None:
                self._session.close()
                self._final = list(self._session.trajectory())
                self._session = None
                release_memory()


def _flatten(stats: dict, prefix: str = "") -> dict:
    """Nested stats -> ``{"a.b": scalar}``; lists and other non-scalars are left out."""
    flat: dict = {}
    for k, v in stats.items():
        if isinstance(v, dict):
            flat.update(_flatten(v, f"{prefix}{k}."))
        elif isinstance(v, np.generic) and v.ndim == 0:
            flat[f"{prefix}{k}"] = v.item()
        elif isinstance(v, (bool, int, float, str)) or v is None:
            flat[f"{prefix}{k}"] = v
    return flat
