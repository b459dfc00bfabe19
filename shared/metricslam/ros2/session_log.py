"""Feed an :class:`~metricslam.ros2.mcap_log.McapLog` from a SLAM session as it runs.

The session's own outputs only: each frame's :class:`PoseEstimate`, its keyframe images, the
local window's landmarks, the optimized trajectory (:meth:`SlamSession.trajectory`) whenever it
changed, each keyframe's depth answer and its scale record (learned and ground scale, their
disagreement, the health flag, and the back end's scale σ read when the record arrives) from
the back end's typed events (:class:`~metricslam.slam.events.ScaleMeasured`,
:class:`~metricslam.slam.events.ScaleHealthUpdated`) — never by wrapping the session's inputs.

Frames: every pose, path and landmark cloud written while the session runs is in its own world
frame (parent ``<cam>/world``): ``run --map`` places the session in the map only after the run.
With a ``localization`` (``run --mcap --map``) that relocalized, :meth:`SessionRecorder.finish`
writes one more, last path: the trajectory ``run`` writes to ``--out``, in the map frame (from
the first localized frame on; parent frame ``map``), and — when the session's world is metric, so
``S_map_world`` is rigid — the ``map`` -> ``<cam>/world`` transform on ``/tf_static``, stamped at
the first frame: everything recorded in the world frame shows in the map, as ``--out`` places it.

Example (what ``metricslam run SEQ --mcap run.mcap`` does)::

    with McapLog("run.mcap", "cam0") as log:
        recorder = SessionRecorder(log, pipeline)
        for frame in frames:
            recorder.after_frame(frame, pipeline.process(frame))
        pipeline.close()
        recorder.close()   # the final optimized path; closes the file
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from metricslam.datasets.base import Frame
from metricslam.geometry import se3, sim3
from metricslam.ros2.mcap_log import McapLog
from metricslam.slam.events import LoopAccepted, ScaleHealthUpdated, ScaleMeasured, Solved, WarpApplied, scale_record
from metricslam.slam.map.localization import MAP_FRAME
from metricslam.slam.pipeline import window_landmarks_world
from metricslam.slam.types import PoseEstimate

log = logging.getLogger(__name__)

#: |log scale| of ``S_map_world`` under which the session's world is rigidly in the map (a metric
#: world's alignment is rigid by construction, :meth:`Relocalizer.S_map_world`)
RIGID_LOG_SCALE = 1e-6


def valid_trajectory(session: object) -> tuple[np.ndarray, np.ndarray]:
    """``(t_ns (N,), T_world_cam (N, 4, 4))`` of the frames of ``session.trajectory()`` that have
    a pose (own or interpolated; placeholders left out)."""
    return valid_poses(session.trajectory())


def valid_poses(estimates: list[PoseEstimate]) -> tuple[np.ndarray, np.ndarray]:
    """``(t_ns (N,), T (N, 4, 4))`` of the ``estimates`` that have a pose, in their own frame."""
    kept = [e for e in estimates if getattr(e, "pose_valid", True)]
    t_ns = np.array([e.t_ns for e in kept], dtype=np.int64)
    T = np.array([e.T_world_cam for e in kept], dtype=np.float64).reshape(len(kept), 4, 4)
    return t_ns, T


class SessionRecorder:
    """Writes one session's outputs to ``mcap_log``.

    Args:
        mcap_log: the file.
        session: a :class:`~metricslam.slam.types.SlamSession`; its ``backend.events`` (if any)
            supply depth maps and say when the optimized trajectory changed.
        localization: the session's :class:`~metricslam.slam.map.localization.MapLocalization`
            (``run --map``): the final path in the map frame too (module docstring).
    """

    def __init__(self, mcap_log: McapLog, session: object, localization: object | None = None) -> None:
        self.log = mcap_log
        self.session = session
        self._localization = localization
        self._path_dirty = threading.Event()
        self._first_t_ns: int | None = None
        self._last_t_ns = 0
        self._camera = None
        backend = getattr(session, "backend", None)
        self._backend = backend
        self._events = getattr(backend, "events", None)
        if self._events is not None:
            self._events.subscribe(self._on_depth, ScaleMeasured)
            self._events.subscribe(self._on_change, Solved, WarpApplied, LoopAccepted)
            self._events.subscribe(self._on_scale_health, ScaleHealthUpdated)

    def _on_depth(self, ev: ScaleMeasured) -> None:
        if ev.inv_depth_map_per_m is not None:
            self.log.keyframe_depth(ev.t_ns, ev.inv_depth_map_per_m, self._camera, ev.image_size)

    def _on_scale_health(self, ev: ScaleHealthUpdated) -> None:
        self.log.scale_health(ev.t_ns, scale_record(ev, self._backend), ev.warning)

    def _on_change(self, ev: object) -> None:
        self._path_dirty.set()

    def after_frame(self, frame: Frame, est: PoseEstimate) -> None:
        """Log one processed frame: its pose; at a keyframe its image and the window's
        landmarks; the optimized path when a keyframe or a global solve changed it."""
        self._last_t_ns = max(self._last_t_ns, int(est.t_ns))
        self._first_t_ns = int(est.t_ns) if self._first_t_ns is None else self._first_t_ns
        if frame.camera is not None:
            self._camera = frame.camera  # the keyframes' intrinsics, for their depth grids' CameraInfo
        self.log.pose(est.t_ns, est.T_world_cam)
        if est.is_keyframe:
            if frame.image is not None:
                self.log.keyframe_image(est.t_ns, frame.image, frame.camera)
            points = window_landmarks_world(self.session)
            if points is not None:
                self.log.landmarks(est.t_ns, points)
            self._path_dirty.set()
        if self._path_dirty.is_set():
            self._path_dirty.clear()
            self.log.path(est.t_ns, *valid_trajectory(self.session))

    def finish(self) -> None:
        """After the session closed: the final optimized path (session world) and, when the
        session relocalized into a ``localization``'s map, that path in the map frame (the last
        path message); stop listening to events."""
        if self._events is not None:
            self._events.unsubscribe(self._on_depth)
            self._events.unsubscribe(self._on_change)
            self._events.unsubscribe(self._on_scale_health)
        trajectory = self.session.trajectory()
        self.log.path(self._last_t_ns, *valid_poses(trajectory))
        if self._localization is None:
            return
        try:
            S_map_world = self._localization.refresh(force=True)  # the final solve's
            mapped = self._localization.map_trajectory(trajectory) if S_map_world is not None else []
        except Exception:  # noqa: BLE001 -- a run failing half way still gets its file closed
            log.exception("mcap: the final path in the map frame could not be estimated")
            return
        t_ns, T_map_cam = valid_poses(mapped)
        if len(t_ns):
            self.log.path(self._last_t_ns, t_ns, T_map_cam, frame_id=MAP_FRAME)
            R, t, s = sim3.split(np.asarray(S_map_world, float))
            if abs(np.log(s)) < RIGID_LOG_SCALE:
                self.log.map_to_world(self._first_t_ns or 0, se3.from_rt(R, t))
            else:  # a world in VO units (learned scale never established): no rigid transform
                log.info("mcap: no map -> world transform: the session's world is not metric "
                         "(S_map_world scale %.4f)", s)

    def close(self) -> None:
        """:meth:`finish`, then close the file (whatever happened: a run that failed half way
        still leaves a readable file)."""
        try:
            self.finish()
        finally:
            self.log.close()
