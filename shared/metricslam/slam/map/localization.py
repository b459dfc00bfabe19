"""One session placed in a saved map — the logic ``run --map`` and the SLAM service share.

:class:`MapLocalization` owns a :class:`~metricslam.slam.map.relocalizer.Relocalizer` attached to
one pipeline and keeps the current ``S_map_world`` (4, 4 Sim(3): session world → map frame,
metres per session world unit): it is re-estimated from every verified match against the back
end's latest solve whenever a match verified or a solve finished since the last estimate
(:meth:`MapLocalization.refresh`); rigid once the session's learned scale is established and
the map is metric (``metric_world`` of :meth:`Relocalizer.S_map_world`). ``run --map`` asks once, after the run, and maps the final
trajectory (:meth:`MapLocalization.map_trajectory`); the live service wraps the session in
:class:`MapFrameSession`, which refreshes after each frame and publishes every pose from then on
as the rigid ``T_map_cam`` (frame id ``"map"``), mapped by ``S_map_world_live``: a session placed
before its learned scale was established keeps the network-depth alignment until it agrees with
rigid (:data:`LIVE_RIGID_LOG_SCALE`), its scale meanwhile fitted to where the matches place their
keyframes once they spread (:data:`LIVE_SPAN_MIN_M`). Frames and units: ``docs/conventions.md``;
the relocalization itself: ``docs/maps.md``.

:func:`open_map` (load + camera/depth-model check) and :func:`save_session_map` (build + atomic
save) are the two file operations both callers use.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.datasets.base import Frame
from metricslam.geometry import sim3
from metricslam.slam.events import Solved
from metricslam.slam.graph.config import LoopConfig
from metricslam.slam.map.format import SavedMap, load_map, save_map
from metricslam.slam.map.relocalizer import MIN_AGREEING_MATCHES, Relocalizer, to_map_frame
from metricslam.slam.types import PoseEstimate

log = logging.getLogger(__name__)

#: the frame ids a pose can be in: the session's own world frame, or the loaded map's
WORLD_FRAME, MAP_FRAME = "world", "map"
#: agreeing matches before a live session switches to the map frame (the relocalizer's own rule)
MIN_LIVE_MATCHES = MIN_AGREEING_MATCHES
#: a session placed in the map before its learned scale was established keeps mapping its live
#: poses by the matches' network-depth scale until that estimate is within this |log scale| of
#: rigid: the graph's own scale converges for tens of frames after it is declared established
#: (KITTI raw 0013: ~14 % over frames 35-60), and a rigid S_map_world before then put the live
#: poses metres off (``MapLocalization.S_map_world_live``)
LIVE_RIGID_LOG_SCALE = 0.01
#: until then (not rigid), the live alignment's scale and translation are fitted to where the
#: agreeing matches place their keyframes in the map once this many place them this far apart
#: (metres from their centroid): one view's network depth reads the scale ±10-20 %, positions
#: spread along the path read it within a few per cent (``docs/history/rule_live_map_early_session24.md``)
LIVE_SPAN_MIN_MATCHES, LIVE_SPAN_MIN_M = 3, 5.0


def open_map(path: str | Path, camera: PinholeCamera, depth_model_id: str | None) -> SavedMap:
    """Load the map at ``path`` and check it was built with ``camera`` and this depth model.

    Raises:
        MapError: one line naming the problem (``format.load_map``, ``SavedMap.check_fits``).
    """
    saved = load_map(path)
    saved.check_fits(camera, depth_model_id, path)
    return saved


def session_map(pipeline, depth_model_id: str | None, metric: bool, source: dict | None = None) -> SavedMap:
    """The map of ``pipeline`` in its own world frame (closed, or running: its back end's
    estimator is held while the keyframes and loop database are read,
    :meth:`GlobalBackend.exclusive`).

    Raises:
        MapError: nothing to save (no global graph, no loop database, too short a session).
    """
    from metricslam.slam.map.builder import map_from_session

    hold = getattr(pipeline.backend, "exclusive", None)
    if callable(hold):
        with hold():
            return map_from_session(pipeline, depth_model_id, metric, source)
    return map_from_session(pipeline, depth_model_id, metric, source)


def save_session_map(pipeline, path: str | Path, depth_model_id: str | None, metric: bool,
                     source: dict | None = None) -> dict:
    """:func:`session_map` saved to ``path`` atomically; returns ``{"path", "keyframes", "save_s"}``.

    Raises:
        MapError: nothing to save, or the folder cannot be written (a previous map there is
            left as it was).
    """
    t0 = time.perf_counter()
    saved = session_map(pipeline, depth_model_id, metric, source)
    save_map(saved, path)
    return {"path": str(path), "keyframes": saved.n_keyframes, "save_s": time.perf_counter() - t0}


class MapLocalization:
    """A session's relocalization into ``saved`` (module docstring).

    Args:
        saved: the loaded map (checked against the session's camera and depth model).
        camera: the session's camera.
        config: loop parameters of the relocalizer's retrieval and verification.
        path: the map's path, for messages and stats.
    """

    def __init__(self, saved: SavedMap, camera: PinholeCamera, config: LoopConfig | None = None,
                 path: str | Path = "map") -> None:
        self.saved = saved
        self.path = str(path)
        self.relocalizer = Relocalizer(saved, camera, config, early_after_relocalized=True)
        self._backend = None
        self._lock = threading.Lock()
        self._dirty = threading.Event()  # a solve finished since refresh()
        self._n_matches = 0  # the relocalizer's match version at the last estimate
        self.S_map_world: np.ndarray | None = None
        #: what the live poses are mapped by (:class:`MapFrameSession`): :attr:`S_map_world`, except
        #: for a session placed before its learned scale was established, which keeps the
        #: network-depth (non-rigid) estimate against the graph of the moment until it agrees with
        #: rigid (:data:`LIVE_RIGID_LOG_SCALE`), its scale fitted to the matches' spread until then
        #: (:meth:`_span_fitted`); the final trajectory always uses :attr:`S_map_world`
        self.S_map_world_live: np.ndarray | None = None
        self._live_rigid = False
        self.matches_used = 0
        self.matches_rejected = 0

    def attach(self, pipeline) -> None:
        """Query every keyframe ``pipeline`` marginalizes; refresh after each of its solves."""
        self._backend = pipeline.backend
        self.relocalizer.attach(pipeline)
        pipeline.backend.events.subscribe(lambda ev: self._dirty.set(), Solved)

    @property
    def first_frame(self) -> int | None:
        """The frame being processed when enough matches first agreed (None: not yet)."""
        return self.relocalizer.first_frame

    def refresh(self, force: bool = False) -> np.ndarray | None:
        """Re-estimate ``S_map_world`` (and ``S_map_world_live``) from every match against the back
        end's latest solve when something changed since the last call (or ``force``); returns
        ``S_map_world`` (None: not relocalized)."""
        n = self.relocalizer.version
        if not (force or n != self._n_matches or (n and self._dirty.is_set())):
            return self.S_map_world
        self._dirty.clear()
        metric = self.saved.metric and bool(getattr(self._backend, "scale_established", False))
        poses = self._backend.optimized_keyframe_poses()
        S, used, rejected = self.relocalizer.S_map_world(poses, metric_world=metric)
        S_live = S
        if metric and not self._live_rigid:
            S_pre = (None if self.S_map_world_live is None  # placed in a metric world: rigid at once
                     else self.relocalizer.S_map_world(poses, metric_world=False)[0])
            if S_pre is None or abs(np.log(sim3.scale(S_pre))) < LIVE_RIGID_LOG_SCALE:
                self._live_rigid = True
            else:
                S_live = S_pre
        if S_live is not None and (not metric or S_live is not S):
            S_live = self._span_fitted(S_live, poses)
        with self._lock:
            self._n_matches = n
            if S is not None:
                self.S_map_world, self.matches_used, self.matches_rejected = S, used, rejected
                self.S_map_world_live = S_live
            return self.S_map_world

    def _span_fitted(self, S_live: np.ndarray, poses: dict[int, np.ndarray]) -> np.ndarray:
        """``S_live`` (4, 4) with its scale and translation fitted (least squares, its rotation
        kept: a fitted one is unobservable about the direction of travel on a straight street) to
        where the matches that agree with it place their keyframes in the map, once
        :data:`LIVE_SPAN_MIN_MATCHES` of them span :data:`LIVE_SPAN_MIN_M`; else ``S_live``."""
        agreeing = self.relocalizer.agreeing(S_live, poses, metric_world=False)
        if len(agreeing) < LIVE_SPAN_MIN_MATCHES:
            return S_live
        p_map = np.array([self.relocalizer.map_position_m(m) for m, _ in agreeing])
        p_world = np.array([p for _, p in agreeing])
        if np.linalg.norm(p_map - p_map.mean(axis=0), axis=1).max() < LIVE_SPAN_MIN_M:
            return S_live
        R = sim3.split(S_live)[0]
        a, b = (p_world - p_world.mean(axis=0)) @ R.T, p_map - p_map.mean(axis=0)
        s = float(np.sum(a * b) / np.sum(a * a))
        if not (np.isfinite(s) and s > 0):
            return S_live
        return sim3.from_rts(R, p_map.mean(axis=0) - s * R @ p_world.mean(axis=0), s)

    def map_trajectory(self, trajectory: list[PoseEstimate]) -> list[PoseEstimate]:
        """The poses from :attr:`first_frame` on, in the map frame (empty: not relocalized)."""
        S, first = self.S_map_world, self.first_frame
        if S is None or first is None:
            return []
        return [dataclasses.replace(e, T_world_cam=to_map_frame(S, e.T_world_cam))
                for e in trajectory if e.frame_index >= first]

    def stats(self, n_frames: int, n_kept: int) -> dict:
        """What ``run --json`` reports as ``map`` (``docs/maps.md``)."""
        reloc, S = self.relocalizer, self.S_map_world
        return {"path": self.path, "relocalized": S is not None and self.first_frame is not None,
                "first_localized_frame": self.first_frame if S is not None else None,
                "unlocalized_frames": n_frames - n_kept, "relocalization_queries": reloc.n_queries,
                "relocalization_query_ms_mean": float(sum(reloc.query_ms) / max(len(reloc.query_ms), 1)),
                "relocalization_matches": len(reloc.matches), "matches_used": self.matches_used,
                "matches_rejected": self.matches_rejected, "map_keyframes": self.saved.n_keyframes,
                "S_map_world": None if S is None else S.tolist(),
                "matched_frames": [[m.kf_frame, m.map_kf_id, m.frame_now, m.n_inliers] for m in reloc.matches]}


class MapFrameSession:
    """A :class:`~metricslam.slam.types.SlamSession` whose poses are in the loaded map's frame
    once it relocalized (the SLAM service's camera sessions with ``SLAM_MAP``).

    Before relocalization every pose is the inner session's own (``frame_id == "world"``); from
    the first frame processed after ``S_map_world`` became known, each pose is the rigid
    ``T_map_cam`` (``frame_id == "map"``, metres) and :meth:`trajectory` answers the map-frame
    poses from :attr:`MapLocalization.first_frame` on, as ``run --map`` writes them.
    ``S_map_world`` is adopted only inside :meth:`process`, so :attr:`frame_id` and
    :meth:`trajectory` agree for a caller that holds the frame loop's lock.

    Args:
        inner: the pipeline session (with a back end).
        localization: its :class:`MapLocalization` (attached here).
        on_relocalized: called once, on the frame thread, with ``(frame_index, detail)``.
        min_matches: verified matches that must agree (:data:`MIN_LIVE_MATCHES`) before the
            session switches to the map frame.
    """

    def __init__(self, inner, localization: MapLocalization,
                 on_relocalized: Callable[[int, str], None] | None = None,
                 min_matches: int = MIN_LIVE_MATCHES) -> None:
        self.inner = inner
        self.min_matches = min_matches
        self.localization = localization
        localization.attach(inner)
        self._on_relocalized = on_relocalized
        self._S: np.ndarray | None = None
        self.first_map_frame: int | None = None  # the first frame published in the map frame

    @property
    def frame_id(self) -> str:
        """``"map"`` once relocalized, else ``"world"``."""
        return WORLD_FRAME if self._S is None else MAP_FRAME

    @property
    def S_map_world(self) -> np.ndarray | None:
        """The adopted (4, 4) Sim(3) session world → map, or None before relocalization."""
        return self._S

    def process(self, frame: Frame) -> PoseEstimate:
        est = self.inner.process(frame)
        try:
            self.localization.refresh()
            S = self.localization.S_map_world_live
        except Exception:  # noqa: BLE001 -- a failed estimate keeps the previous one
            log.exception("map: re-estimating S_map_world at frame %d failed", frame.index)
            S = self._S
        if S is not None and self._S is None and self.localization.matches_used < self.min_matches:
            S = None  # not yet: wait for a second match that agrees
        if S is not None and self._S is None:
            self.first_map_frame = int(est.frame_index)
            loc = self.localization
            m = loc.relocalizer.matches[0]
            detail = (f"relocalized into map {loc.path} at frame {est.frame_index} ({loc.matches_used} of "
                      f"{len(loc.relocalizer.matches)} matches agree; the first verified at frame {m.frame_now}: "
                      f"keyframe {m.kf_frame} = map keyframe {m.map_kf_id}, {m.n_inliers} inliers; "
                      f"scale {float(np.cbrt(np.linalg.det(S[:3, :3]))):.4f})")
            log.info(detail)
            self._S = S  # before the callback: it may read frame_id
            if self._on_relocalized is not None:
                self._on_relocalized(int(est.frame_index), detail)
        self._S = S if S is not None else self._S
        if self._S is None:
            return est
        return dataclasses.replace(est, T_world_cam=to_map_frame(self._S, np.asarray(est.T_world_cam, float)))

    def trajectory(self) -> list[PoseEstimate]:
        """World-frame poses before relocalization; map-frame poses from the first localized frame
        on after it (:meth:`MapLocalization.map_trajectory`)."""
        poses = self.inner.trajectory()
        if self._S is None:
            return poses
        self.localization.refresh()  # the back end may have solved again since the last frame
        return self.localization.map_trajectory(poses)

    def stats(self) -> dict:
        stats = dict(self.inner.stats())
        loc = self.localization
        stats["map"] = {"relocalized": self._S is not None, "first_map_frame": self.first_map_frame,
                        "relocalization_queries": loc.relocalizer.n_queries,
                        "relocalization_matches": len(loc.relocalizer.matches),
                        "matches_used": loc.matches_used, "matches_rejected": loc.matches_rejected}
        return stats

    def close(self) -> None:
        self.inner.close()
        if self._S is not None:
            self.localization.refresh(force=True)  # the final solve

    def __getattr__(self, name: str):
        # the back end, VO, ... of the inner session (map topics, viewer, odometry)
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)
