"""The SLAM service's saved map (``SLAM_MAP`` / ``--map``): a thin adapter over
:mod:`metricslam.slam.map.localization`, the logic ``metricslam run --map`` uses too.

* **At start** the map is loaded and checked once. A missing, truncated or corrupt map, a newer
  schema, an unreadable depth model: one error line in the log and in the health answer
  (``map.error``), and the service runs **without** a map — it never dies of its map.
* **Each camera session** is checked against the map (camera intrinsics, depth model id); a
  foreign camera gets a ``map_refused`` status event and runs without the map. Otherwise its
  session is a :class:`~metricslam.slam.map.localization.MapFrameSession`: poses in the session's
  own world frame (``frame_id "world"``) until a keyframe verifies against the map, then a
  ``relocalized`` status event and every pose, keyframe, path, landmark and odometry message in
  the map frame (``frame_id "map"``, metres).
* **Saving**: the queryable ``metricslam/_service/map/save/<camera_id>`` (payload: the folder)
  writes atomically the camera's current session map — once it relocalized, the loaded map
  extended by it (:mod:`metricslam.slam.map.merge`: map keyframes fixed, the matches as
  cross-session factors, the session's keyframes appended); a failed save answers one error line
  and leaves any previous map there intact.

With a map, a camera's new session (roll-over, restart, return after an idle close) does not
continue its earlier poses: each session is placed by relocalizing into the map.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Callable

from metricslam.camera import PinholeCamera
from metricslam.errors import CodecError, MapError, MetricSlamError
from metricslam.slam.map.format import SavedMap, depth_model_id, load_map, save_map
from metricslam.slam.map.localization import MapFrameSession, MapLocalization, session_map
from metricslam.slam.map.merge import merge_session
from metricslam.slam.system_config import SystemConfig
from metricslam.slam.types import SlamSession
from metricslam.wire import keys

log = logging.getLogger(__name__)
SessionFactory = Callable[[str, PinholeCamera], SlamSession]
#: ``(camera_id, event, detail)``: publishes a one-off status event of the camera
EventSink = Callable[[str, str, str], None]



def camera_of_query(query) -> str | None:
    """The camera id that ends a ``…/<camera_id>`` query's key (the service's per-camera
    queryables); None after answering a malformed one with its one-line error."""
    camera_id = str(query.key_expr).rsplit("/", 1)[-1]
    try:
        keys.check_camera_id(camera_id)
    except CodecError as exc:
        query.reply_err(str(exc).encode())
        return None
    return camera_id


class ServiceMap:
    """The map a SLAM service localizes its cameras in (module docstring).

    Args:
        path: the map folder (None: no map).
        config: the sessions' system config (scale mode, depth model, loop parameters).
    """

    def __init__(self, path: str | Path | None, config: SystemConfig) -> None:
        self.path = None if path is None else str(path)
        self.config = config
        self.saved: SavedMap | None = None
        self.error: str | None = None
        self.model_id: str | None = None
        try:
            if config.use_scale:
                from metricslam.depth.model import DEFAULT_MODEL_PATH
                self.model_id = depth_model_id(config.depth.model_path or DEFAULT_MODEL_PATH)
            if path is not None:
                self.saved = load_map(path)
                log.info("map %s loaded: %d keyframes (%s); each camera session relocalizes into it",
                         path, self.saved.n_keyframes, "metric" if self.saved.metric else "VO units")
        except MapError as exc:
            self.error = str(exc)
            log.error("%s; the SLAM service runs without a map", exc)

    def health(self) -> dict:
        """The ``map`` entry of the service's health answer."""
        return {"path": self.path, "loaded": self.saved is not None, "error": self.error,
                "keyframes": None if self.saved is None else self.saved.n_keyframes}

    def wrap(self, factory: SessionFactory, on_event: EventSink) -> SessionFactory:
        """``factory`` whose sessions relocalize into the map (unchanged without a map)."""
        if self.saved is None:
            return factory

        def make(camera_id: str, camera: PinholeCamera) -> SlamSession:
            session = factory(camera_id, camera)
            if getattr(session, "backend", None) is None:  # identity / VO only: nothing to relocalize
                return session
            try:
                self.saved.check_fits(camera, self.model_id, self.path)
            except MapError as exc:
                log.error("camera %s: %s; it runs without the map", camera_id, exc)
                on_event(camera_id, "map_refused", f"{exc}; this camera runs without the map")
                return session
            loc = MapLocalization(self.saved, camera, self.config.graph_config().loop, self.path)
            return MapFrameSession(session, loc, lambda frame, detail: on_event(camera_id, "relocalized", detail))

        return make

    def on_save_query(self, query, worker_of: Callable[[str], object], serves: Callable[[str], bool]) -> None:
        """``metricslam/_service/map/save/<camera_id>`` (payload: the folder): answers the JSON of
        :meth:`save` or one error line; a service that does not serve the camera stays silent."""
        camera_id = camera_of_query(query)
        if camera_id is None:
            return
        if not serves(camera_id):
            return
        worker = worker_of(camera_id)
        target = query.payload.to_bytes().decode(errors="replace").strip() if query.payload is not None else ""
        try:
            if worker is None:
                raise MapError(f"camera {camera_id} has no running SLAM session to save (no frames yet, or closed)")
            answer = self.save(worker, target)
        except MetricSlamError as exc:
            log.error("camera %s: map save failed: %s", camera_id, exc)
            query.reply_err(str(exc).splitlines()[0].encode())
            return
        except Exception as exc:  # noqa: BLE001 -- a failed save must never hurt the service
            log.exception("camera %s: map save failed", camera_id)
            query.reply_err(f"map save failed: {type(exc).__name__}: {exc}".splitlines()[0].encode())
            return
        query.reply(keys.map_save_key(camera_id), json.dumps(answer).encode())

    def save(self, worker, target: str) -> dict:
        """Save ``worker``'s current session map to ``target`` (the save query; between two frames).

        Returns ``{"camera_id", "path", "keyframes", "frame_id", "save_s", "extended"}`` (the
        merge's stats once relocalized, else None).

        Raises:
            MapError: one line — no folder named, no running session, nothing to save yet,
                the folder cannot be written.
        """
        if not target:
            raise MapError("name the folder to save the map to in the query's payload")
        t0 = time.perf_counter()

        def build(session) -> tuple[SavedMap, object, str]:
            loc = getattr(session, "localization", None) if getattr(session, "S_map_world", None) is not None else None
            source = {"camera_id": worker.camera_id, "mode": self.config.mode}
            metric_world = bool(getattr(getattr(session, "backend", None), "scale_established", False))
            own = session_map(session, self.model_id, self.config.use_scale, source)
            return own, (loc, metric_world), worker.frame_id

        built = worker.with_session(build)
        if built is None:
            raise MapError(f"camera {worker.camera_id} has no running SLAM session to save")
        own, (loc, metric_world), frame_id = built
        extended = None
        if loc is not None:  # relocalized: the loaded map extended by this session (merge.py)
            own, extended = merge_session(loc.saved, own, loc.relocalizer, loc.S_map_world,
                                          loc.saved.metric and metric_world)
        save_map(own, target)
        answer = {"camera_id": worker.camera_id, "path": str(target), "keyframes": own.n_keyframes,
                  "frame_id": frame_id, "save_s": time.perf_counter() - t0, "extended": extended}
        log.info("camera %s: map saved: %s", worker.camera_id, json.dumps(answer))
        return answer

