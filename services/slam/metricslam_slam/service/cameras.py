"""The SLAM service's cameras: how many run, when one is closed, and what outlives it.

* **A cap** (``max_cameras``): a frame for a new camera id while that many cameras run is
  dropped and counted (``refused_frames`` in the health answer), and a ``camera_refused`` status
  goes out on the camera's status key (at most once per status period per camera). Without it,
  every new ``metricslam/<id>/frame`` key — 500 garbage ids, say — got a thread forever.
* **Idle close** (``camera_idle_timeout_s``): a camera with no frame for that long is closed
  from the status loop: its worker thread stops, its session (and the session's own threads and
  memory) is closed, a ``camera_closed`` status is published.
* **What outlives a camera**: its final trajectory, answerable on ``…/trajectory`` for
  ``closed_trajectory_ttl_s`` (at most ``max_closed_trajectories`` cameras, oldest dropped) and,
  with ``state_dir``, on disk (:class:`~metricslam_slam.service.trajectory_store.TrajectoryStore`).
  When the camera comes back — or the service restarts — its new session continues from its
  last pose (:class:`~metricslam_slam.service.continued_session.ContinuedSession`), unless its
  frames go backwards from it (a second replay): then a fresh session starts and the earlier
  trajectory is forgotten (:meth:`Cameras.forget_prior`; on disk it is moved aside).
* **Reset** (:meth:`Cameras.reset`, the service's ``metricslam/_service/reset/<camera_id>``
  queryable, ``metricslam replay --new-session``): the camera's next frame starts a fresh
  session whatever its index; nothing earlier is continued.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Callable

from metricslam.slam.types import PoseEstimate
from metricslam.wire.codec import Message, StatusMessage
from metricslam_slam.service.camera_worker import CameraWorker
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.trajectory_store import TrajectoryStore

log = logging.getLogger(__name__)
#: camera ids remembered for rate-limiting refusal statuses
_MAX_REFUSED_IDS = 1024


def event_status(camera_id: str, event: str, detail: str, base: StatusMessage | None = None) -> StatusMessage:
    """A one-off status carrying ``event`` (on top of a camera's current status, or zeros)."""
    if base is None:
        base = StatusMessage(camera_id=camera_id, t_ns=time.time_ns(), frames_received=0, frames_processed=0,
                             queue_drops=0, malformed=0, queue_depth=0, fps=0.0)
    return base.model_copy(update={"event": event, "event_detail": detail[:1000], "t_ns": time.time_ns()})


class Cameras:
    """The running :class:`CameraWorker` of each camera and the trajectories of closed ones.

    Args:
        settings: ``max_cameras``, ``camera_idle_timeout_s``, ``closed_trajectory_ttl_s``,
            ``max_closed_trajectories``, ``state_dir``, ``status_period_s``.
        make_worker: builds the worker of a new camera id.
        put: publishes ``(camera_id, topic, message)``.
        status_of: a worker's current :class:`StatusMessage` (with the service's depth link).
        on_close: called with the camera id after its worker closed (map publisher cleanup).
    """

    def __init__(self, settings: SlamServiceSettings, make_worker: Callable[[str], CameraWorker],
                 put: Callable[[str, str, Message], None],
                 status_of: Callable[[CameraWorker], StatusMessage],
                 on_close: Callable[[str], None] = lambda camera_id: None) -> None:
        self.settings = settings
        self._make_worker = make_worker
        self._put = put
        self._status_of = status_of
        self._on_close = on_close
        self._lock = threading.Lock()
        self._workers: dict[str, CameraWorker] = {}
        self._closed: collections.OrderedDict[str, tuple[float, list[PoseEstimate]]] = collections.OrderedDict()
        self._refusals: collections.OrderedDict[str, float] = collections.OrderedDict()
        self._closing: dict[str, threading.Event] = {}  # camera id -> set once its close is done
        # camera id -> why its next worker must start a fresh session (a reset with no worker running)
        self._pending_resets: collections.OrderedDict[str, str] = collections.OrderedDict()
        self._accepting = True
        self._closed_frame_ids: dict[str, str] = {}  # camera id -> frame id of its last closed trajectory
        self.store = TrajectoryStore(settings.state_dir) if settings.state_dir is not None else None
        self.refused_frames = 0
        self.refused_cameras = 0  # distinct ids among the last _MAX_REFUSED_IDS refused
        self.cameras_closed = 0
        self.malformed_closed = 0  # malformed frames of cameras closed since

    # -- frames (zenoh's callback thread) ----------------------------------------------------
    def offer(self, camera_id: str, payload: bytes) -> bool:
        """Queue a frame for its camera, starting the camera if there is room; False if refused."""
        for _ in range(2):  # a worker closing right now refuses; the second try makes a new one
            with self._lock:
                if not self._accepting:
                    return False
                worker = self._workers.get(camera_id)
                if worker is None and len(self._workers) < self.settings.max_cameras:
                    worker = self._workers[camera_id] = self._make_worker(camera_id)
                    reset_why = self._pending_resets.pop(camera_id, None)
                    if reset_why is not None:
                        worker.request_new_session(reset_why)
            if worker is None:
                self._refuse(camera_id)
                return False
            if worker.offer(payload):
                return True
            with self._lock:
                if self._workers.get(camera_id) is worker:
                    del self._workers[camera_id]
        return False

    def _refuse(self, camera_id: str) -> None:
        now = time.monotonic()
        with self._lock:
            self.refused_frames += 1
            self.refused_cameras += camera_id not in self._refusals
            last = self._refusals.get(camera_id)
            if last is not None and now - last < self.settings.status_period_s:
                return
            self._refusals[camera_id] = now
            self._refusals.move_to_end(camera_id)
            while len(self._refusals) > _MAX_REFUSED_IDS:
                self._refusals.popitem(last=False)
        detail = (f"the SLAM service already runs max_cameras={self.settings.max_cameras} cameras; frames of "
                  f"{camera_id!r} are dropped until one closes (idle after "
                  f"{self.settings.camera_idle_timeout_s:g} s) or SLAM_MAX_CAMERAS is raised")
        if self.refused_cameras <= 5 or self.refused_cameras % 100 == 0:
            log.warning("camera %s refused (%d refused so far): %s", camera_id, self.refused_cameras, detail)
        self._put(camera_id, "status", event_status(camera_id, "camera_refused", detail))

    # -- lookups -----------------------------------------------------------------------------
    def get(self, camera_id: str) -> CameraWorker | None:
        with self._lock:
            return self._workers.get(camera_id)

    def workers(self) -> list[CameraWorker]:
        with self._lock:
            return list(self._workers.values())

    def ids(self) -> list[str]:
        with self._lock:
            return sorted(self._workers)

    def closed_trajectory(self, camera_id: str) -> list[PoseEstimate] | None:
        """A closed camera's final trajectory while it is kept, else the one in ``state_dir``
        (e.g. from before a restart), else None."""
        return self.closed_framed_trajectory(camera_id)[1]

    def closed_framed_trajectory(self, camera_id: str) -> tuple[str, list[PoseEstimate] | None]:
        """``(frame_id, poses)`` of :meth:`closed_trajectory`, read together: ``"map"`` when the
        camera had relocalized into the service's map before it closed (kept in memory, or
        stored in ``state_dir``: :meth:`TrajectoryStore.load_framed`), else ``"world"``."""
        self._expire(time.monotonic())
        with self._lock:
            entry = self._closed.get(camera_id)
            frame_id = self._closed_frame_ids.get(camera_id, "world")
        if entry is not None:
            return frame_id, entry[1]
        frame_id, poses = self.store.load_framed(camera_id) if self.store is not None else ("world", [])
        return frame_id, poses or None

    def prior_poses(self, camera_id: str) -> list[PoseEstimate]:
        """What a new session of ``camera_id`` continues: its closed trajectory, else the one on
        disk (``state_dir``), else nothing."""
        with self._lock:
            closing = self._closing.get(camera_id)
        if closing is not None:  # came back while its old session is still closing: wait for it
            closing.wait(60.0)
        with self._lock:
            entry = self._closed.pop(camera_id, None)
        if entry is not None:
            return entry[1]
        return self.store.load(camera_id) if self.store is not None else []

    def forget_prior(self, camera_id: str) -> None:
        """A fresh session replaces the camera's earlier trajectory: drop the closed one and move
        the file in ``state_dir`` aside (``<camera_id>.poses.previous.jsonl``), so neither is
        continued later."""
        with self._lock:
            closing = self._closing.get(camera_id)
        if closing is not None:
            closing.wait(60.0)
        with self._lock:
            self._closed.pop(camera_id, None)
        if self.store is not None:
            try:
                moved = self.store.set_aside(camera_id)
            except OSError as exc:
                log.error("camera %s: cannot move its earlier trajectory aside: %s", camera_id, exc)
            else:
                if moved is not None:
                    log.info("camera %s: earlier trajectory moved to %s", camera_id, moved)

    def reset(self, camera_id: str, why: str) -> int:
        """Make the camera's next frame start a fresh session (``why`` is said in its
        ``session_restarted`` status); returns how many earlier poses will not be continued."""
        with self._lock:
            worker = self._workers.get(camera_id)
            if worker is None:
                self._pending_resets[camera_id] = why
                self._pending_resets.move_to_end(camera_id)
                while len(self._pending_resets) > _MAX_REFUSED_IDS:
                    self._pending_resets.popitem(last=False)
        if worker is not None:
            worker.request_new_session(why)
            return len(worker.trajectory())
        earlier = self.closed_trajectory(camera_id) or []
        self.forget_prior(camera_id)
        return len(earlier)

    def record_pose(self, camera_id: str, pose: object) -> None:
        """Persist a published pose (no-op without ``state_dir``)."""
        if self.store is not None:
            try:
                self.store.append(camera_id, pose)
            except OSError as exc:
                log.error("camera %s: cannot persist a pose: %s", camera_id, exc)

    def publish_event(self, worker: CameraWorker, event: str, detail: str) -> None:
        log.info("camera %s: %s: %s", worker.camera_id, event, detail)
        self._put(worker.camera_id, "status", event_status(worker.camera_id, event, detail, self._status_of(worker)))

    def stats(self) -> dict:
        with self._lock:
            return {"max_cameras": self.settings.max_cameras, "refused_frames": self.refused_frames,
                    "cameras_closed": self.cameras_closed, "closed_cameras": sorted(self._closed),
                    "malformed_frames": self.malformed_closed + sum(w.malformed for w in self._workers.values())}

    # -- closing -----------------------------------------------------------------------------
    def close_idle(self) -> int:
        """Close the cameras idle for ``camera_idle_timeout_s``; returns how many."""
        now = time.monotonic()
        with self._lock:
            idle = self._take([c for c, w in self._workers.items()
                               if w.idle_s(now) >= self.settings.camera_idle_timeout_s])
        for worker in idle:
            self._close(worker, f"no frame for {self.settings.camera_idle_timeout_s:g} s")
        self._expire(now)
        return len(idle)

    def finish(self, camera_id: str, why: str) -> bool:
        """Close the camera now, as :meth:`close_idle` does (its final trajectory is kept);
        False when it has no running session."""
        with self._lock:
            taken = self._take([camera_id])
        for worker in taken:
            self._close(worker, why)
        return bool(taken)

    def close_all(self) -> None:
        """Stop taking cameras and close every one (service stop)."""
        with self._lock:
            self._accepting = False
            workers = self._take(list(self._workers))
        for worker in workers:
            self._close(worker, "the SLAM service is stopping")
        if self.store is not None:
            self.store.close()

    def _take(self, camera_ids: list[str]) -> list[CameraWorker]:
        """Remove these cameras' workers and mark each as closing (the caller holds the lock and
        closes them after releasing it: a close runs the final solve)."""
        taken = [self._workers.pop(c) for c in camera_ids if c in self._workers]
        for worker in taken:
            self._closing[worker.camera_id] = threading.Event()
        return taken

    def _close(self, worker: CameraWorker, why: str) -> None:
        frame_id = "world"
        try:
            worker.close()
            frame_id, poses = worker.framed_trajectory()
        except Exception:  # noqa: BLE001 -- one camera's failure must not stop the others closing
            log.exception("camera %s: closing failed", worker.camera_id)
            poses = []
        with self._lock:
            self.cameras_closed += 1
            self.malformed_closed += worker.malformed
            if poses and self.settings.closed_trajectory_ttl_s > 0 and self.settings.max_closed_trajectories > 0:
                self._closed[worker.camera_id] = (time.monotonic(), poses)
                self._closed.move_to_end(worker.camera_id)
                while len(self._closed) > self.settings.max_closed_trajectories:
                    self._closed.popitem(last=False)
            # "map": it had relocalized into the service's map; kept only beside a kept trajectory
            self._closed_frame_ids = {k: v for k, v in self._closed_frame_ids.items() if k in self._closed}
            if worker.camera_id in self._closed:
                self._closed_frame_ids[worker.camera_id] = frame_id
        if poses and self.store is not None:
            try:
                self.store.rewrite(worker.camera_id, poses, frame_id)
            except OSError as exc:
                log.error("camera %s: cannot write its final trajectory: %s", worker.camera_id, exc)
        with self._lock:
            done = self._closing.pop(worker.camera_id, None)
        if done is not None:
            done.set()
        self._on_close(worker.camera_id)
        where = "" if self.store is None else f"; written to {self.store.path(worker.camera_id)}"
        self.publish_event(worker, "camera_closed", f"{why}; final trajectory of {len(poses)} poses kept "
                           f"for {self.settings.closed_trajectory_ttl_s:g} s on …/trajectory{where}")

    def _expire(self, now: float) -> None:
        with self._lock:
            while self._closed:
                camera_id, (closed_at, _) = next(iter(self._closed.items()))
                if now - closed_at < self.settings.closed_trajectory_ttl_s:
                    break
                del self._closed[camera_id]
