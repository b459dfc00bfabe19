"""Rerun view of SLAM sessions (rerun-sdk, the optional ``viz`` extra, imported only when a
:class:`RerunView` is made): the SLAM service's live view (``slam-service --rerun``) and the
offline recording of ``metricslam run --rerun out.rrd`` use this one class, so both recordings
hold the same entities. It lives in the core (it needs only core types and rerun) so the CLI's
offline run does not import a service.

One recording per camera. Entities (world = the SLAM world frame, camera frame x right,
y down, z forward as in docs/conventions.md)::

    world/<cam>/camera            Transform3D T_world_cam + Pinhole (the current frame)
    world/<cam>/camera/image      the input image (JPEG-compressed)
    world/<cam>/trajectory        LineStrips3D of the published camera positions
    world/<cam>/keyframes         Points3D of keyframe positions
    world/<cam>/landmarks         Points3D of the local window's landmarks (VO world)
    world/keyframe_depth          DepthImage (metres) of each keyframe the depth source answered
                                  for (logged from the back end's depth worker as answers arrive)
    scale/<cam>/<name>            Scalars per keyframe scale record (the back end's
                                  ScaleHealthUpdated events, on the "frame" and "t" timelines of
                                  the keyframe): learned, ground (m per keyframe VO unit),
                                  disagreement_log, learned_spread_log, sigma_log (the back end's
                                  σ of log scale), warning (1 = the sources disagree)

``target`` is ``web`` (gRPC server + web viewer on localhost; the log says the URL) or a path
ending in ``.rrd`` (a recording file; ``rerun FILE.rrd`` opens it).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np

from metricslam.datasets.base import Frame
from metricslam.errors import ConfigError
from metricslam.slam.events import SCALE_RECORD_VALUES, ScaleHealthUpdated, ScaleMeasured, scale_record
from metricslam.slam.pipeline import window_landmarks_world
from metricslam.slam.types import PoseEstimate

log = logging.getLogger(__name__)


class RerunView:
    """Logs frames, poses, keyframes, landmarks and depth maps of every camera."""

    def __init__(self, target: str, application_id: str = "metricslam") -> None:
        try:
            import rerun as rr
        except ImportError:
            raise ConfigError("--rerun needs rerun-sdk, the optional viz extra: pip install -e '.[viz]' "
                              "(or pip install 'metricslam[viz]')") from None
        self._rr = rr
        self._rec = rr.RecordingStream(application_id)
        if target == "web":
            uri = self._rec.serve_grpc()
            rr.serve_web_viewer(connect_to=uri, open_browser=False)
            log.info("rerun web viewer serving %s", uri)
        elif target.endswith(".rrd"):
            Path(target).parent.mkdir(parents=True, exist_ok=True)
            self._rec.save(target)
        else:
            raise ConfigError(f"--rerun must be 'web' or a path ending in .rrd, got {target!r}")
        self._lock = threading.Lock()
        self._positions: dict[str, list[np.ndarray]] = {}
        self._keyframes: dict[str, list[np.ndarray]] = {}

    def log(self, camera_id: str, frame: Frame, est: PoseEstimate, session: object) -> None:
        """Log one processed frame (never raises: a viewer must not disturb SLAM)."""
        try:
            with self._lock:
                self._log(camera_id, frame, est, session)
        except Exception:  # noqa: BLE001 -- viewing is best effort
            log.exception("rerun logging failed for camera %s", camera_id)

    def _log(self, cid: str, frame: Frame, est: PoseEstimate, session: object) -> None:
        rr, rec = self._rr, self._rec
        base = f"world/{cid}"
        rec.set_time("frame", sequence=frame.index)
        rec.set_time("t", timestamp=frame.t_ns * 1e-9)
        T = np.asarray(est.T_world_cam, dtype=float)
        rec.log(f"{base}/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]),
                rr.Pinhole(image_from_camera=frame.camera.K,
                           resolution=[frame.camera.width_px, frame.camera.height_px]))
        rec.log(f"{base}/camera/image", rr.Image(frame.image).compress(jpeg_quality=75))
        self._positions.setdefault(cid, []).append(T[:3, 3].copy())
        rec.log(f"{base}/trajectory", rr.LineStrips3D([np.array(self._positions[cid])]))
        if est.is_keyframe:
            self._keyframes.setdefault(cid, []).append(T[:3, 3].copy())
            rec.log(f"{base}/keyframes", rr.Points3D(np.array(self._keyframes[cid]), radii=0.3))
            points = window_landmarks_world(session)
            if points is not None and len(points):
                rec.log(f"{base}/landmarks", rr.Points3D(points, radii=0.05))

    def attach(self, session: object, camera_id: str | None = None) -> None:
        """Subscribe to a session's back-end events (``session.backend.events``): each keyframe's
        depth map (:class:`~metricslam.slam.events.ScaleMeasured`) goes to :meth:`log_depth`, each
        scale record (:class:`~metricslam.slam.events.ScaleHealthUpdated`) to ``scale/<camera_id>``.
        A session without a back end (``vo_only``) has neither to show."""
        backend = getattr(session, "backend", None)
        if backend is not None and hasattr(backend, "events"):
            backend.events.subscribe(self._on_scale_measured, ScaleMeasured)
            base = f"scale/{camera_id}" if camera_id else "scale"
            backend.events.subscribe(lambda ev: self.log_scale(base, ev, scale_record(ev, backend)),
                                     ScaleHealthUpdated)

    def observing(self, factory):
        """Wrap a session factory so every new session is :meth:`attach`-ed."""
        def make(camera_id, camera):
            session = factory(camera_id, camera)
            self.attach(session, camera_id)
            return session
        return make

    def log_scale(self, base: str, ev: ScaleHealthUpdated, values: dict[str, float | None]) -> None:
        """One keyframe's scale record as scalars under ``base`` (NaN or None: not logged)."""
        try:
            with self._lock:
                rr, rec = self._rr, self._rec
                rec.set_time("frame", sequence=int(ev.frame_index))  # this thread's time only
                rec.set_time("t", timestamp=ev.t_ns * 1e-9)
                for name in SCALE_RECORD_VALUES:
                    value = values.get(name)
                    if value is not None and np.isfinite(value):
                        rec.log(f"{base}/{name}", rr.Scalars(float(value)))
                rec.log(f"{base}/warning", rr.Scalars(float(ev.warning)))
        except Exception:  # noqa: BLE001 -- viewing is best effort
            log.exception("rerun scale logging failed")

    def _on_scale_measured(self, ev: ScaleMeasured) -> None:
        if ev.inv_depth_map_per_m is not None:
            self.log_depth(ev.inv_depth_map_per_m)

    def log_depth(self, inv_depth_per_m: np.ndarray) -> None:
        """Log one keyframe's metric depth map (the back end's ScaleMeasured events)."""
        try:
            with self._lock:
                inv = np.asarray(inv_depth_per_m, dtype=np.float32)
                depth_m = np.where(inv > 1e-3, 1.0 / np.maximum(inv, 1e-3), 0.0).astype(np.float32)
                self._rec.log("world/keyframe_depth", self._rr.DepthImage(depth_m, meter=1.0))
        except Exception:  # noqa: BLE001 -- viewing is best effort
            log.exception("rerun depth logging failed")

    def close(self) -> None:
        self._rec.flush()
        self._rec.disconnect()
