"""Per camera: publish what the map did — ``…/path``, ``…/landmarks``, ``…/keyframe_depth``.

Fed by the session's own outputs (after each processed frame) and its back end's typed events
(:mod:`metricslam.slam.events`), never by wrapping the session's inputs:

* ``keyframe_depth`` — each :class:`ScaleMeasured` with an answer (emitted on the back end's
  depth thread, published from there);
* ``landmarks`` — the local window's depth-known landmarks after every keyframe;
* all in the session's frame: ``frame_id "map"`` once it relocalized into the service's saved map;
* ``path`` — the optimized trajectory (frames with a pose) when it changed: after a keyframe, a
  global solve, an accepted loop or a warp. Building it is O(frames), once per change; a
  continued session's earlier poses come as stored arrays
  (:meth:`~metricslam_slam.service.continued_session.ContinuedSession.path_columns`), so only
  the current session's frames are gathered pose by pose.

A session without a local VO or back end (the ``identity`` transport session) publishes none.
"""

from __future__ import annotations

import logging
import threading
from typing import Callable

import numpy as np

from metricslam.datasets.base import Frame
from metricslam.slam.pipeline import window_landmarks_world
from metricslam.slam.events import LoopAccepted, ScaleMeasured, Solved, WarpApplied
from metricslam.slam.types import PoseEstimate
from metricslam.wire.codec import Message, TrajectoryMessage
from metricslam.wire.map_messages import KeyframeDepthMessage, LandmarksMessage

log = logging.getLogger(__name__)
Publish = Callable[[str, Message], None]  # (topic, message) of one camera


class MapPublisher:
    """Publishes one camera's map topics (module docstring).

    Args:
        camera_id: the camera.
        session: its :class:`~metricslam.slam.types.SlamSession`.
        publish: sends ``(topic, message)`` on ``metricslam/<camera_id>/<topic>``.
    """

    def __init__(self, camera_id: str, session: object, publish: Publish) -> None:
        self.camera_id = camera_id
        self.session = session
        self._publish = publish
        self._path_dirty = threading.Event()
        self._events = getattr(getattr(session, "backend", None), "events", None)
        if self._events is not None:
            self._events.subscribe(self._on_depth, ScaleMeasured)
            self._events.subscribe(self._on_change, Solved, WarpApplied, LoopAccepted)

    def _on_depth(self, ev: ScaleMeasured) -> None:
        if ev.inv_depth_map_per_m is None:
            return
        width_px, height_px = ev.image_size
        self._publish("keyframe_depth", KeyframeDepthMessage(
            camera_id=self.camera_id, frame_index=ev.frame_index, t_ns=max(ev.t_ns, 0),
            image_width_px=width_px, image_height_px=height_px,
            inv_depth_per_m=np.asarray(ev.inv_depth_map_per_m, dtype=np.float32)))

    def _on_change(self, ev: object) -> None:
        self._path_dirty.set()

    def after_frame(self, frame: Frame, est: PoseEstimate) -> None:
        """Called on the camera's worker thread after each frame (never raises)."""
        try:
            if est.is_keyframe:
                self._publish_landmarks(est)
            if self._path_dirty.is_set() and hasattr(self.session, "trajectory"):
                self._path_dirty.clear()
                self._publish_path()
        except Exception:  # noqa: BLE001 -- publishing the map must never stop tracking
            log.exception("camera %s: map publishing failed", self.camera_id)

    def _publish_landmarks(self, est: PoseEstimate) -> None:
        points = window_landmarks_world(self.session)
        if points is None:
            return
        T_world_origin = getattr(self.session, "T_world_origin", None)  # a continued session
        if T_world_origin is not None:
            points = points @ T_world_origin[:3, :3].T + T_world_origin[:3, 3]
        S_map_world = getattr(self.session, "S_map_world", None)  # relocalized into the service's map
        if S_map_world is not None:
            points = points @ S_map_world[:3, :3].T + S_map_world[:3, 3]
        self._path_dirty.set()  # a new keyframe extends the optimized trajectory
        self._publish("landmarks", LandmarksMessage(
            camera_id=self.camera_id, frame_index=est.frame_index, t_ns=est.t_ns,
            scale_established=est.scale_established, frame_id=self._frame_id(),
            points_world=points.astype(np.float32)))

    def _frame_id(self) -> str:
        return getattr(self.session, "frame_id", "world")

    def _publish_path(self) -> None:
        path_columns = getattr(self.session, "path_columns", None)  # a continued session
        if path_columns is not None:
            frame_index, t_ns, T_world_cam, state_code, scale_established = path_columns()
            self._publish("path", TrajectoryMessage(
                camera_id=self.camera_id, scale_established=scale_established, frame_id=self._frame_id(),
                frame_index=frame_index,
                t_ns=t_ns, T_world_cam=T_world_cam, state_code=state_code))
            return
        kept = [e for e in self.session.trajectory() if e.pose_valid]
        n = len(kept)
        self._publish("path", TrajectoryMessage(
            camera_id=self.camera_id, scale_established=bool(kept and kept[-1].scale_established),
            frame_id=self._frame_id(), frame_index=np.array([e.frame_index for e in kept], dtype=np.int64),
            t_ns=np.array([e.t_ns for e in kept], dtype=np.int64),
            T_world_cam=np.array([e.T_world_cam for e in kept], dtype=np.float64).reshape(n, 4, 4),
            state_code=TrajectoryMessage.state_codes([e.state for e in kept])))

    def close(self) -> None:
        """Stop listening to the back end's events."""
        if self._events is not None:
            self._events.unsubscribe(self._on_depth)
            self._events.unsubscribe(self._on_change)
