"""Each camera's trajectory on disk, so it survives a restart of the SLAM service.

One JSON-lines file per camera, ``<state_dir>/<camera_id>.poses.jsonl``, one pose per line::

    {"frame_index": 12, "t_ns": 1200000000, "state": "tracking", "segment_id": 0,
     "is_keyframe": false, "scale_established": true, "pose_valid": true, "scale_state": "metric",
     "frame_id": "world", "T_world_cam": [16 floats, row-major]}

``frame_id`` is the pose's frame (:data:`~metricslam.wire.base.FrameId`): ``"world"``, the
session's own, or ``"map"`` once the camera relocalized into the service's saved map
(``T_world_cam`` is then ``T_map_cam``, metres); a line without it (written before the field
existed) is ``"world"``. :meth:`TrajectoryStore.load_framed` answers the frame id with the poses,
so a restarted service labels a map-frame trajectory ``"map"`` (``…/trajectory``).

While a camera runs, every published pose is appended (line-buffered: a killed process loses
at most the line being written; a torn last line is skipped on reading). When a camera's
session closes cleanly (idle, rolled over, service stopping) the file is rewritten, atomically,
with the final optimized trajectory. A restarted service reads it back and continues the camera
(:mod:`metricslam_slam.service.continued_session`). When a fresh session replaces it (frames went
backwards, a reset) the file is moved aside to ``<camera_id>.poses.previous.jsonl`` (one kept).
"""

from __future__ import annotations

import json
import logging
import os
import threading
from pathlib import Path
from typing import IO

import numpy as np

from metricslam.errors import ServiceError
from metricslam.slam.map.localization import MAP_FRAME, WORLD_FRAME
from metricslam.slam.types import PoseEstimate, ScaleState, TrackingState
from metricslam.wire import keys

log = logging.getLogger(__name__)


def pose_record(est: object, frame_id: str | None = None) -> dict:
    """One line's fields from a :class:`PoseEstimate` or a :class:`PoseMessage`; ``frame_id``:
    the pose's frame (default: the message's own ``frame_id``, else ``"world"``)."""
    frame_id = frame_id or getattr(est, "frame_id", None) or WORLD_FRAME
    return {"frame_index": int(est.frame_index), "t_ns": int(est.t_ns), "state": TrackingState(est.state).value,
            "segment_id": int(est.segment_id), "is_keyframe": bool(est.is_keyframe),
            "scale_established": bool(est.scale_established),
            "pose_valid": bool(getattr(est, "pose_valid", True)),
            "scale_state": ScaleState(getattr(est, "scale_state", None) or ScaleState.UNSCALED).value,
            "frame_id": str(frame_id), "T_world_cam": [float(v) for v in np.asarray(est.T_world_cam, dtype=np.float64).reshape(16)]}


def parse_record(line: str) -> PoseEstimate:
    """A line back to a :class:`PoseEstimate`; raises ValueError/KeyError/TypeError on a bad line."""
    return parse_framed_record(line)[1]


def parse_framed_record(line: str) -> tuple[str, PoseEstimate]:
    """A line back to ``(frame_id, PoseEstimate)`` (no ``frame_id`` field: ``"world"``); raises
    ValueError/KeyError/TypeError on a bad line."""
    r = json.loads(line)
    T = np.array(r["T_world_cam"], dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(T)):
        raise ValueError("non-finite pose")
    frame_id = r.get("frame_id", WORLD_FRAME)
    if frame_id not in (WORLD_FRAME, MAP_FRAME):
        raise ValueError(f"unknown frame_id {frame_id!r}")
    return frame_id, PoseEstimate(int(r["frame_index"]), int(r["t_ns"]), T, TrackingState(r["state"]),
                        is_keyframe=bool(r["is_keyframe"]), segment_id=int(r["segment_id"]),
                        scale_established=bool(r["scale_established"]), pose_valid=bool(r["pose_valid"]),
                        scale_state=ScaleState(r.get("scale_state", ScaleState.UNSCALED.value)))


class TrajectoryStore:
    """The per-camera pose logs under ``state_dir`` (module docstring). Thread-safe.

    Raises:
        ServiceError: ``state_dir`` cannot be created.
    """

    def __init__(self, state_dir: str | Path) -> None:
        self.state_dir = Path(state_dir)
        try:
            self.state_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ServiceError(f"cannot create the state directory {self.state_dir}: {exc}; "
                               "set SLAM_STATE_DIR to a writable folder") from None
        self._files: dict[str, IO[str]] = {}
        self._lock = threading.Lock()

    def path(self, camera_id: str) -> Path:
        return self.state_dir / f"{keys.check_camera_id(camera_id)}.poses.jsonl"

    def load(self, camera_id: str) -> list[PoseEstimate]:
        """The camera's stored poses in order ([] when none); unreadable lines are skipped."""
        return self.load_framed(camera_id)[1]

    def load_framed(self, camera_id: str) -> tuple[str, list[PoseEstimate]]:
        """``(frame_id, poses)``: the frame of the camera's last stored pose (``"world"`` when
        none) and its stored poses in that frame, in order. A file the live poses were appended
        to by a session that relocalized and was then killed holds its world-frame poses before
        the switch too: those are left out, as the live ``…/trajectory`` leaves them out.
        Unreadable lines are skipped."""
        path = self.path(camera_id)
        if not path.is_file():
            return WORLD_FRAME, []
        framed, bad = [], 0
        with self._lock, path.open() as f:
            for line in f:
                try:
                    framed.append(parse_framed_record(line))
                except (ValueError, KeyError, TypeError):
                    bad += 1
        if bad:
            log.warning("camera %s: skipped %d unreadable line(s) of %s (a torn write?)", camera_id, bad, path)
        frame_id = framed[-1][0] if framed else WORLD_FRAME
        return frame_id, [est for f_id, est in framed if f_id == frame_id]

    def append(self, camera_id: str, est: object) -> None:
        """Append one published pose (a :class:`PoseMessage`, in its ``frame_id``, or a
        :class:`PoseEstimate`, ``"world"``)."""
        line = json.dumps(pose_record(est), separators=(",", ":")) + "\n"
        with self._lock:
            f = self._files.get(camera_id)
            if f is None:
                f = self._files[camera_id] = self.path(camera_id).open("a", buffering=1)
            f.write(line)

    def rewrite(self, camera_id: str, poses: list[PoseEstimate], frame_id: str = WORLD_FRAME) -> None:
        """Replace the camera's file with ``poses`` (its final trajectory, all in ``frame_id``),
        atomically."""
        path = self.path(camera_id)
        tmp = path.with_suffix(".jsonl.tmp")
        with self._lock:
            f = self._files.pop(camera_id, None)
            if f is not None:
                f.close()
            with tmp.open("w") as out:
                out.writelines(json.dumps(pose_record(p, frame_id), separators=(",", ":")) + "\n" for p in poses)
                out.flush()
                os.fsync(out.fileno())
            tmp.replace(path)

    def set_aside(self, camera_id: str) -> Path | None:
        """Move the camera's file to ``<camera_id>.poses.previous.jsonl`` (replacing an older
        one), so the next pose starts a new file; returns where it went, or None without one."""
        path = self.path(camera_id)
        previous = path.with_name(f"{camera_id}.poses.previous.jsonl")
        with self._lock:
            f = self._files.pop(camera_id, None)
            if f is not None:
                f.close()
            if not path.is_file():
                return None
            path.replace(previous)
        return previous

    def close(self) -> None:
        with self._lock:
            for f in self._files.values():
                f.close()
            self._files.clear()
