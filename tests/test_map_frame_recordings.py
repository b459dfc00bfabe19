"""The map frame in MCAP recordings and in ``state_dir`` (docs/maps.md, "MCAP and state_dir").

* :class:`McapLog` names a pose's parent frame as the live ROS 2 bridge does (one function,
  :func:`~metricslam.ros2.rmw_zenoh.parent_frame_id`): ``map`` for ``frame_id="map"``;
* ``run --mcap --map`` (:class:`SessionRecorder` with the run's localization): the live poses
  stay in the session's world, the last path is the ``--out`` trajectory in the map frame;
* :class:`TrajectoryStore` lines carry ``frame_id``; a line without one (written before) reads
  back as ``"world"``.

Over the service (``poses --mcap``, a restart with ``state_dir``): tests/test_slam_service_map_frames.py.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from metricslam.datasets.base import Frame
from metricslam.slam.types import PoseEstimate, TrackingState
from metricslam.wire.camera_messages import PoseMessage
from metricslam_slam.service.sessions import IdentitySession
from metricslam_slam.service.trajectory_store import TrajectoryStore
from tests.ros2_cdr import CdrReader
from tests.test_mcap_recording import read_mcap

pytest.importorskip("mcap")
SHIFT_M = 100.0  # the stand-in map frame is the session world moved 100 m along x


def _T(x_m: float, z_m: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3], T[2, 3] = x_m, z_m
    return T


def _parents(topics: dict, topic: str) -> list[str]:
    """Each message's ``header.frame_id`` (a TFMessage's: its one transform's)."""
    parents = []
    for m in topics[topic]:
        r = CdrReader(m[2])
        if topic == "/tf":
            assert r.u32() == 1
        parents.append(r.header()[2])
    return parents


def test_mcap_log_names_the_parent_frame_as_the_ros2_bridge_does(tmp_path: Path) -> None:
    from metricslam.ros2.mcap_log import McapLog
    from metricslam.wire.map_messages import LandmarksMessage
    from metricslam_slam.service.ros2_bridge import parent_frame

    with McapLog(tmp_path / "f.mcap", camera_id="cam-1") as log:
        for i, frame_id in enumerate(("world", "map")):
            log.pose(i, _T(i, 0.0), frame_id)
            log.path(i, np.array([i]), _T(i, 0.0)[None], frame_id)
            log.landmarks(i, np.zeros((2, 3)), frame_id)
    topics = read_mcap(tmp_path / "f.mcap")
    expected = ["cam_1/world", "map"]
    for leaf in ("pose", "path", "landmarks"):
        assert _parents(topics, f"/metricslam/cam_1/{leaf}") == expected, leaf
    assert _parents(topics, "/tf") == expected
    bridge = [parent_frame("cam-1", LandmarksMessage(camera_id="cam-1", frame_index=0, t_ns=0, frame_id=f,
                                                     points_world=np.zeros((0, 3), np.float32)))
              for f in ("world", "map")]
    assert bridge == expected


class _ShiftLocalization:
    """Stands in for the run's :class:`MapLocalization` after it relocalized at frame 2: the map
    frame is the world moved :data:`SHIFT_M` along x (what ``MapRun.finish`` would write), and
    scaled by ``scale`` (1: a metric world, rigidly in the map)."""

    first_frame = 2

    def __init__(self, scale: float = 1.0) -> None:
        self.scale = scale

    def refresh(self, force: bool = False) -> np.ndarray:
        S = np.diag([self.scale] * 3 + [1.0])
        S[0, 3] = SHIFT_M
        return S

    def map_trajectory(self, trajectory: list[PoseEstimate]) -> list[PoseEstimate]:
        return [dataclasses.replace(e, T_world_cam=self.refresh() @ e.T_world_cam)
                for e in trajectory if e.frame_index >= self.first_frame]


def _record_run(path: Path, localization: _ShiftLocalization) -> dict:
    from metricslam.ros2.mcap_log import McapLog
    from metricslam.ros2.session_log import SessionRecorder

    session = IdentitySession()
    with McapLog(path, camera_id="cam0") as log:
        recorder = SessionRecorder(log, session, localization)
        for i in range(5):
            frame = Frame(index=i, t_ns=1_000 + i, image=None, camera=None)
            recorder.after_frame(frame, session.process(frame))
        session.close()
        recorder.close()
    return read_mcap(path)


def test_run_mcap_with_a_map_labels_the_final_map_frame_path_map(tmp_path: Path) -> None:
    topics = _record_run(tmp_path / "run.mcap", _ShiftLocalization())
    assert _parents(topics, "/metricslam/cam0/pose") == ["cam0/world"] * 5  # live: the session's world
    paths = topics["/metricslam/cam0/path"]
    assert [CdrReader(m[2]).header()[2] for m in paths[-2:]] == ["cam0/world", "map"]
    r = CdrReader(paths[-1][2])
    r.header()
    n = r.u32()
    stamps, xs = [], []
    for _ in range(n):
        stamps.append(r.header()[:2])
        xs.append(r.pose()[0])
    assert n == 3 and xs == [SHIFT_M] * 3  # frames 2..4, in the map frame: the --out trajectory


def test_run_mcap_with_a_map_places_the_world_frame_in_the_map_when_it_is_metric(tmp_path: Path) -> None:
    """The live poses were recorded in the session's world: one ``/tf_static`` ``map`` ->
    ``cam0/world`` (the final S_map_world, stamped at the first frame) shows them in the map beside
    the map-frame path. A world in VO units (S_map_world not rigid) gets none: a TF cannot scale."""
    topics = _record_run(tmp_path / "run.mcap", _ShiftLocalization())
    (log_time, _, raw, *_), = topics["/tf_static"]
    r = CdrReader(raw)
    assert r.u32() == 1
    sec, nanosec, parent = r.header()
    assert (parent, r.string()) == ("map", "cam0/world") and sec * 10**9 + nanosec == log_time == 1_000
    np.testing.assert_allclose(r.f64s(3), [SHIFT_M, 0.0, 0.0])
    np.testing.assert_allclose(np.abs(r.f64s(4)), [0.0, 0.0, 0.0, 1.0])  # no rotation
    assert "/tf_static" not in _record_run(tmp_path / "vo_units.mcap", _ShiftLocalization(scale=2.0))


def test_the_store_keeps_the_frame_id_and_reads_old_lines_as_world(tmp_path: Path) -> None:
    store = TrajectoryStore(tmp_path)

    def message(i: int, frame_id: str) -> PoseMessage:
        return PoseMessage(camera_id="cam0", frame_index=i, t_ns=i, state="tracking", frame_id=frame_id,
                           T_world_cam=_T(SHIFT_M if frame_id == "map" else 0.0, i))

    for i, frame_id in enumerate(["world"] * 2 + ["map"] * 3):  # live lines of a session killed after relocalizing
        store.append("cam0", message(i, frame_id))
    store.close()
    frame_id, poses = store.load_framed("cam0")
    assert frame_id == "map" and [p.frame_index for p in poses] == [2, 3, 4]
    store.rewrite("cam0", poses, "map")  # a clean close: the final trajectory
    assert store.load_framed("cam0")[0] == "map" and len(store.load("cam0")) == 3
    # a file written before lines carried frame_id
    old = {"frame_index": 0, "t_ns": 0, "state": "tracking", "segment_id": 0, "is_keyframe": False,
           "scale_established": True, "pose_valid": True, "T_world_cam": np.eye(4).reshape(16).tolist()}
    store.path("cam1").write_text(json.dumps(old) + "\n")
    frame_id, poses = store.load_framed("cam1")
    assert frame_id == "world" and len(poses) == 1
    est = PoseEstimate(0, 0, np.eye(4), TrackingState.TRACKING)
    store.rewrite("cam2", [est])
    assert json.loads(store.path("cam2").read_text())["frame_id"] == "world"
