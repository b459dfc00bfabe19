"""The SLAM service: Zenoh in, one SLAM session per camera, poses/keyframes/status out.

Subscribes ``metricslam/*/frame``; each camera id gets a :class:`CameraWorker` (bounded
drop-oldest queue + its own SlamSession). Publishes ``…/pose`` for every processed frame,
``…/keyframe`` per keyframe, ``…/status`` every ``status_period_s``, and the map topics
``…/path``, ``…/landmarks``, ``…/keyframe_depth`` (:class:`MapPublisher`); with ``ros2`` on, a
:class:`~metricslam_slam.service.ros2_bridge.Ros2Bridge` mirrors them as ROS 2 topics and takes
``sensor_msgs`` camera input; answers the queryables
``…/trajectory`` (whole current trajectory), ``metricslam/_service/health`` (JSON; its
``instance`` and ``started_t_ns`` change when the service restarts, which is how ``replay`` and
``poses`` tell a restart from a slow service) and ``metricslam/_service/reset/<camera_id>`` (the
camera's next frame starts a fresh session; the query's payload, if any, is the reason given)
and, with a saved map (``SLAM_MAP``), ``metricslam/_service/map/save/<camera_id>``
(:mod:`~metricslam_slam.service.service_map`).
A :class:`~metricslam_slam.service.watchdog.Watchdog` ends the process when a camera or the
status loop hangs (``hang_timeout_s``), so that compose or Kubernetes restarts it.
Messages on keys that are not a valid camera id are counted (``unrouted``) and dropped.
"""

from __future__ import annotations

import json
import logging
import threading
import time
import uuid

import numpy as np
import zenoh

from metricslam.errors import CodecError, ServiceError
from metricslam.slam.config_file import load_system_config
from metricslam.slam.events import SegmentRelocalized, Solved
from metricslam.slam.system_config import LIVE_PROFILE, SystemConfig
from metricslam.wire import keys
from metricslam.wire.codec import Message, TrajectoryMessage, encode
from metricslam_slam.service.camera_commands import CameraCommands
from metricslam_slam.service.camera_worker import CameraWorker
from metricslam_slam.service.cameras import Cameras
from metricslam_slam.service.map_publisher import MapPublisher
from metricslam_slam.service.memory import trim_heap
from metricslam_slam.service.service_map import ServiceMap
from metricslam_slam.service.sessions import SessionFactory, make_session_factory
from metricslam_slam.service.settings import SlamServiceSettings, check_retired_environment
from metricslam_slam.zenoh_config import ZenohAccess, open_client

log = logging.getLogger(__name__)

#: topics published with zenoh's ``BLOCK`` congestion control: a pose for every processed frame
#: (zenoh's default, ``DROP``, discards a sample when the transmit queue is full, as it can be
#: when the service is starved of CPU).
RELIABLE_TOPICS = frozenset({"pose", "odom", "keyframe", "status"})


def congestion_for(topic: str) -> zenoh.CongestionControl:
    """``BLOCK`` for :data:`RELIABLE_TOPICS`, ``DROP`` for the map topics (superseded anyway)."""
    return zenoh.CongestionControl.BLOCK if topic in RELIABLE_TOPICS else zenoh.CongestionControl.DROP


class SlamService:
    """Run with ``with SlamService(settings) as svc: svc.wait()`` (or ``start()``/``stop()``).

    Args:
        settings: service settings (network, depth client, status).
        session_factory: overrides the factory built from ``settings`` (tests, embedding).
        depth_source: overrides the HTTP depth source built from ``settings.depth_url``.
        config: what every camera's session is built from (:func:`build_session`); None:
            :func:`load_system_config` over the live profile
            (:data:`~metricslam.slam.system_config.LIVE_PROFILE`: the initial metric scale on),
            then ``$METRICSLAM_CONFIG`` and ``METRICSLAM_*`` variables.
    """

    def __init__(self, settings: SlamServiceSettings, session_factory: SessionFactory | None = None,
                 depth_source: object | None = None, config: SystemConfig | None = None) -> None:
        check_retired_environment()
        self.settings = settings
        self.config = config if config is not None else load_system_config(profile=LIVE_PROFILE)
        use_scale = self.config.use_scale and settings.session_kind == "pipeline"
        if depth_source is None and use_scale and settings.depth_url:
            from metricslam_slam.service.http_depth import HttpDepthSource
            depth_source = HttpDepthSource(
                settings.depth_url, timeout_s=settings.depth_timeout_s,
                connect_timeout_s=settings.depth_connect_timeout_s,
                retries=settings.depth_retries, backoff_s=settings.depth_backoff_s)
        self.viewer = None
        if settings.rerun:
            from metricslam.rerun_view import RerunView
            self.viewer = RerunView(settings.rerun)
        self.depth_source = depth_source
        factory = session_factory or make_session_factory(
            settings.session_kind, self.config, depth_source)
        self.map = ServiceMap(settings.map, self.config)  # never raises: a bad map is logged, not used
        factory = self.map.wrap(factory, self._map_event)
        factory = factory if self.viewer is None else self.viewer.observing(factory)
        self._factory = factory
        self._maps: dict[str, MapPublisher] = {}
        self.ros2 = None  # the ROS 2 bridge (settings.ros2), made in start()
        self._cameras = Cameras(settings, self._new_worker, self._put,
                                lambda worker: worker.status(*self._depth_link()), self._drop_map)
        self._stopped = threading.Event()
        self._stop_requested = threading.Event()
        self._session: zenoh.Session | None = None
        self._entities: list = []
        self._status_thread: threading.Thread | None = None
        self._status_tick_s = time.monotonic()  # the status loop's last turn (watchdog)
        self._watchdog = None
        self.unrouted = 0
        self.instance = uuid.uuid4().hex[:12]  # tells this run of the service from the next one
        self.started_t_ns = time.time_ns()

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self, connect_timeout_s: float = 30.0) -> "SlamService":
        logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per probe is noise
        log.info("SLAM service settings: %s", self.settings.model_dump())
        access = ZenohAccess()
        log.info("zenoh access: %s", f"authenticating as {access.user!r}" if access.user
                 else "no credentials (ZENOH_ACCESS_USER unset)")
        log.info("SLAM system config (%s): %s", self.config.mode, self.config.model_dump(mode="json"))
        self._check_depth_link()
        if self.settings.ros2:  # fail at start, naming the fix, not on every publish later
            from metricslam_slam.service.ros2_bridge import Ros2Bridge
            Ros2Bridge.check_available()
        deadline = time.monotonic() + connect_timeout_s
        while True:  # the router may come up after us (compose, `up`)
            try:
                self._session = open_client(self.settings.zenoh_endpoint, self.settings.zenoh_mode)
                break
            except ServiceError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        s = self._session
        try:
            self._frame_keys = zenoh.KeyExpr(self.settings.frame_key_expr)
        except zenoh.ZError as exc:
            raise ServiceError(f"frame_key_expr {self.settings.frame_key_expr!r} is not a zenoh key "
                               f"expression: {exc}") from None
        commands = CameraCommands(self._cameras, self._serves, self._stopped.is_set, self.instance)
        self._entities = [
            s.declare_subscriber(self._frame_keys, self._on_frame),
            s.declare_queryable(keys.wildcard("trajectory"), self._on_trajectory_query),
            s.declare_queryable(keys.HEALTH_KEY, self._on_health_query),
            s.declare_queryable(f"{keys.RESET_KEY_PREFIX}/*", commands.on_reset_query),
            s.declare_queryable(f"{keys.FINISH_KEY_PREFIX}/*", commands.on_finish_query),
            s.declare_queryable(f"{keys.MAP_SAVE_KEY_PREFIX}/*",
                                lambda q: self.map.on_save_query(q, self._cameras.get, self._serves)),
        ]
        if self.settings.ros2:
            from metricslam_slam.service.ros2_bridge import Ros2Bridge
            st = self.settings
            self.ros2 = Ros2Bridge(s, st.ros2_domain_id, st.ros2_node_name, self._offer_frame, self._put,
                                   self._serves, st.ros2_position_sigma_m, st.ros2_rotation_sigma_rad,
                                   camera_of=lambda cid: getattr(self._cameras.get(cid), "camera", None))
        self._status_thread = threading.Thread(target=self._status_loop, name="slam-status", daemon=True)
        self._status_tick_s = time.monotonic()
        self._status_thread.start()
        if self.settings.hang_timeout_s > 0 or self.settings.heartbeat_file is not None:
            from metricslam_slam.service.watchdog import Watchdog
            self._watchdog = Watchdog(self.settings.hang_timeout_s or float("inf"), self.stalls,
                                      self.settings.heartbeat_file).start()
        log.info("SLAM service connected to %s; listening on %s", self.settings.zenoh_endpoint,
                 self.settings.frame_key_expr)
        return self

    def stop(self) -> None:
        """Stop taking frames, finish queued ones, close sessions and the zenoh session."""
        if self._stopped.is_set():
            return
        self._stopped.set()
        self._stop_requested.set()
        if self._watchdog is not None:  # closing cameras may take long; that is not a hang
            self._watchdog.stop()
        for entity in self._entities[:1]:
            entity.undeclare()
        if self.ros2 is not None:
            self.ros2.close_inputs()
        if self._status_thread is not None:
            self._status_thread.join(5.0)
        self._cameras.close_all()  # finishes queued frames; final trajectories kept / written
        for entity in self._entities[1:]:
            entity.undeclare()
        for map_publisher in list(self._maps.values()):
            map_publisher.close()
        if self.ros2 is not None:
            self.ros2.close()
        if self._session is not None:
            self._session.close()
        if self.viewer is not None:
            self.viewer.close()
        close = getattr(self.depth_source, "close", None)
        if callable(close):
            close()
        log.info("SLAM service stopped")

    def __enter__(self) -> "SlamService":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def request_stop(self) -> None:
        """Ask :meth:`wait` to return (safe from a signal handler); then call :meth:`stop`."""
        self._stop_requested.set()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until :meth:`request_stop` or :meth:`stop`; True if asked to stop."""
        return self._stop_requested.wait(timeout_s)

    # -- inputs ------------------------------------------------------------------------------
    def _new_worker(self, camera_id: str) -> CameraWorker:
        worker = CameraWorker(
            camera_id, self._factory, lambda topic, msg: self._put(camera_id, topic, msg),
            self.config.queues.frames, self.settings.keyframe_images, self._on_estimate,
            prior_poses=None if self.map.saved is not None else lambda: self._cameras.prior_poses(camera_id),
            on_session=lambda session: self._on_new_session(camera_id, session),
            on_event=lambda event, detail: self._cameras.publish_event(worker, event, detail),
            max_session_keyframes=self.settings.max_session_keyframes,
            forget_prior=lambda: self._cameras.forget_prior(camera_id))
        return worker

    def _on_frame(self, sample: zenoh.Sample) -> None:
        try:
            camera_id, _ = keys.parse_key(str(sample.key_expr))
        except CodecError as exc:
            self.unrouted += 1
            if self.unrouted <= 5:
                log.warning("dropped a frame on an unusable key: %s", exc)
            return
        if not self._stopped.is_set():
            self._cameras.offer(camera_id, sample.payload.to_bytes())

    def _offer_frame(self, camera_id: str, payload: bytes) -> None:
        if not self._stopped.is_set():
            self._cameras.offer(camera_id, payload)

    def _serves(self, camera_id: str) -> bool:
        return self._frame_keys.intersects(zenoh.KeyExpr(keys.key(camera_id, "frame")))

    def _on_new_session(self, camera_id: str, session: object) -> None:
        self._attach_map(camera_id, session)
        events = getattr(getattr(session, "backend", None), "events", None)
        if events is not None and self.settings.heap_trim_period_s > 0:
            events.subscribe(self._after_solve, Solved)
        if events is not None:  # a lost camera put back in its own map: say so beside the poses' jump
            events.subscribe(lambda ev: self._map_event(camera_id, "segment_relocalized", (
                f"tracking segment {ev.segment_id} relocalized in this session's map at frame "
                f"{ev.frame_index} ({ev.n_loops} loops); its poses moved there")), SegmentRelocalized)

    def _attach_map(self, camera_id: str, session: object) -> None:
        """Each new session of a camera gets a :class:`MapPublisher` (path, landmarks and
        keyframe depth of that camera), replacing the one of its previous session."""
        self._drop_map(camera_id)
        self._maps[camera_id] = MapPublisher(
            camera_id, session, lambda topic, msg: self._put(camera_id, topic, msg))

    @staticmethod
    def _after_solve(ev: Solved) -> None:
        """A batch re-solve (each accepted loop) has just freed the old ISAM2 and its own
        temporaries: return those pages now, not at the next periodic trim (seconds later, after
        the next allocations have scattered over them)."""
        if ev.batch:
            trim_heap()

    def _map_event(self, camera_id: str, event: str, detail: str) -> None:
        worker = self._cameras.get(camera_id)
        if worker is not None:
            self._cameras.publish_event(worker, event, detail)

    def _drop_map(self, camera_id: str) -> None:
        old = self._maps.pop(camera_id, None)
        if old is not None:
            old.close()

    def _on_estimate(self, camera_id, frame, est, session) -> None:
        if self.viewer is not None:
            self.viewer.log(camera_id, frame, est, session)
        map_publisher = self._maps.get(camera_id)
        if map_publisher is not None:
            map_publisher.after_frame(frame, est)

    def _put(self, camera_id: str, topic: str, message: Message) -> None:
        """Publish ``message`` on ``metricslam/<camera_id>/<topic>``. Poses, keyframes and
        status events are never dropped under congestion (:data:`RELIABLE_TOPICS`); the map
        topics, which the next update supersedes, may be."""
        if self._session is None:
            return
        if topic == "pose":
            self._cameras.record_pose(camera_id, message)
        try:
            self._session.put(keys.key(camera_id, topic), encode(message),
                              congestion_control=congestion_for(topic))
        except zenoh.ZError as exc:  # session closing; nothing to do but note it
            log.debug("publish on %s/%s failed: %s", camera_id, topic, exc)
        if self.ros2 is not None:
            self.ros2.forward(camera_id, topic, message)

    # -- queryables --------------------------------------------------------------------------
    def _on_trajectory_query(self, query: zenoh.Query) -> None:
        try:
            camera_id, _ = keys.parse_key(str(query.key_expr))
        except CodecError as exc:
            query.reply_err(str(exc).encode())
            return
        worker = self._cameras.get(camera_id)
        frame_id, poses = (worker.framed_trajectory() if worker is not None
                           else self._cameras.closed_framed_trajectory(camera_id))
        if poses is None:
            if self._frame_keys.intersects(zenoh.KeyExpr(keys.key(camera_id, "frame"))):
                query.reply_err(f"no SLAM session for camera {camera_id!r} (no frames yet)".encode())
            return  # another worker owns this camera: stay silent
        n = len(poses)
        message = TrajectoryMessage(
            camera_id=camera_id, scale_established=bool(poses and poses[-1].scale_established), frame_id=frame_id,
            frame_index=np.array([p.frame_index for p in poses], dtype=np.int64),
            t_ns=np.array([p.t_ns for p in poses], dtype=np.int64),
            T_world_cam=np.array([p.T_world_cam for p in poses], dtype=np.float64).reshape(n, 4, 4),
            state_code=TrajectoryMessage.state_codes([p.state for p in poses]))
        query.reply(keys.key(camera_id, "trajectory"), encode(message))

    def _on_health_query(self, query: zenoh.Query) -> None:
        query.reply(keys.HEALTH_KEY, json.dumps(self.health()).encode())

    def health(self) -> dict:
        cameras = self._cameras.ids()
        depth_url, reachable, _, outages = self._depth_link()
        return {"ready": self._session is not None and not self._stopped.is_set(),
                "cameras": cameras, "unrouted": self.unrouted, "depth_url": depth_url,
                "depth_reachable": reachable, "depth_outages": outages,
                "ros2": None if self.ros2 is None else self.ros2.stats(), "instance": self.instance,
                "started_t_ns": self.started_t_ns, "map": self.map.health(), **self._cameras.stats()}

    # -- depth link --------------------------------------------------------------------------
    def _depth_link(self) -> tuple[str | None, bool | None, str | None, int]:
        """``(depth_url, reachable, last_error, outages)`` of the remote depth source; all
        None/0 without one (scale off, or the in-process model)."""
        source = self.depth_source
        if source is None or not hasattr(source, "reachable"):
            return None, None, None, 0
        return (self.settings.depth_url, getattr(source, "reachable", None),
                getattr(source, "last_error", None), int(getattr(source, "outages", 0)))

    def _check_depth_link(self) -> None:
        """Say at start, once, where learned scale comes from; an unreachable depth service is
        logged as an error by the source itself (and again only when its state changes)."""
        if not (self.config.use_scale and self.settings.session_kind == "pipeline"):
            log.info("learned scale factors are OFF (%s): poses are in the VO's arbitrary scale",
                     self.config.mode)
            return
        probe = getattr(self.depth_source, "probe", None)
        if not callable(probe):
            log.info("learned scale factors from the in-process depth model")
        elif probe():
            log.info("learned scale factors from the depth service at %s", self.settings.depth_url)

    # -- status ------------------------------------------------------------------------------
    def stalls(self) -> list[tuple[str, float]]:
        """``(what, seconds without progress)`` of each loop the watchdog watches: the status
        loop (it ticks every ``status_period_s``) and each camera's worker on its frame."""
        now = time.monotonic()
        status_s = now - self._status_tick_s - self.settings.status_period_s
        return [("the status loop", max(0.0, status_s))] + [
            (f"camera {w.camera_id}", w.stalled_s(now)) for w in self._cameras.workers()]

    def _status_loop(self) -> None:
        period = self.settings.heap_trim_period_s
        trimmed_s = time.monotonic()
        while not self._stopped.wait(self.settings.status_period_s):
            self._status_tick_s = time.monotonic()
            probe = getattr(self.depth_source, "probe", None)
            if callable(probe):
                probe()
            self._cameras.close_idle()
            self._publish_status()
            if period > 0 and time.monotonic() - trimmed_s >= period:
                trim_heap()
                trimmed_s = time.monotonic()

    def _publish_status(self) -> None:
        depth_url, reachable, error, outages = self._depth_link()
        for worker in self._cameras.workers():
            try:
                self._put(worker.camera_id, "status",
                          worker.status(depth_url, reachable, error, outages))
            except Exception:  # status is best effort, never fatal
                log.exception("status for camera %s failed", worker.camera_id)
