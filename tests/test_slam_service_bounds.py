"""SLAM service bounds over real zenoh sessions on loopback: a cap on cameras, idle close (the
threads of 200 garbage camera ids come back), closed trajectories kept, a camera coming back
(or a restarted service) continuing from its last pose, session roll-over, and a service killed
mid-stream that continues from its state directory.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from metricslam.camera import PinholeCamera
from metricslam.errors import ServiceError
from metricslam.slam.events import EventBus, Solved
from metricslam.slam.system_config import SystemConfig
from metricslam.slam.types import PoseEstimate, TrackingState
from metricslam.wire import keys
from metricslam_slam.service.sessions import IdentitySession
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.slam_service import SlamService
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import FramePublisher, PoseRecorder, query_health, query_trajectory
from metricslam_slam.zenoh_config import open_client
from tests.child_process import LineReader, interrupt_and_wait

CAMERA = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=31.5, cy_px=23.5, width_px=64, height_px=48)
IMAGE = np.full((48, 64), 7, dtype=np.uint8)


class MovingSession(IdentitySession):
    """Moves 1 m along z per frame from its own origin; a keyframe every 2nd frame."""

    def process(self, frame):
        T = np.eye(4)
        T[2, 3] = float(len(self._poses))
        pose = PoseEstimate(frame.index, frame.t_ns, T, TrackingState.TRACKING,
                            is_keyframe=len(self._poses) % 2 == 1)
        self._poses.append(pose)
        return pose


@pytest.fixture()
def stack(request):
    """(endpoint, client session, start_service(factory=None, **settings))."""
    port = 17600 + zlib.crc32(request.node.name.encode()) % 40
    endpoint = f"tcp/127.0.0.1:{port}"
    router = open_router(endpoint)
    client = open_client(endpoint)
    services: list[SlamService] = []

    def start_service(factory=None, **overrides) -> SlamService:
        settings = SlamServiceSettings(**{"zenoh_endpoint": endpoint, "depth_url": None, "session_kind": "identity",
                                          "status_period_s": 0.1, **overrides})
        svc = SlamService(settings, session_factory=factory,
                          config=SystemConfig(depth={"use_scale": False}, queues={"frames": 64})).start()
        services.append(svc)
        deadline = time.monotonic() + 5
        while query_health(client, 0.5) is None and time.monotonic() < deadline:
            time.sleep(0.05)
        return svc

    yield endpoint, client, start_service
    for svc in services:
        svc.stop()
    client.close()
    router.close()


def _wait(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def _publish(client, camera_id: str, indices) -> None:
    pub = FramePublisher(client, camera_id)
    assert pub.wait_for_subscriber(10), "no SLAM service subscribed to the frames"
    for i in indices:
        pub.publish(i, i * 100_000_000, IMAGE, CAMERA)
    pub.close()


def _trajectory_or_none(client) -> list[int]:
    try:
        return list(query_trajectory(client, "cam0", timeout_s=1.0).frame_index)
    except ServiceError:
        return []


def _os_threads() -> int:
    """Threads of this process as the kernel counts them (zenoh's own included)."""
    status = Path("/proc/self/status").read_text()
    return int(next(line.split()[1] for line in status.splitlines() if line.startswith("Threads:")))


def _camera_threads() -> int:
    return sum(t.name.startswith("slam-") and t.name != "slam-status" for t in threading.enumerate())


def _events(recorder: PoseRecorder) -> list[str]:
    return [s.event for s in recorder.statuses if s.event]


def test_garbage_camera_ids_get_threads_that_are_freed(stack) -> None:
    _, client, start_service = stack
    svc = start_service(max_cameras=250, camera_idle_timeout_s=0.5)
    baseline = _os_threads()
    for i in range(200):
        client.put(keys.key(f"garbage-{i}", "frame"), b"\x00 not a frame " + bytes([i]))
    assert _wait(lambda: svc.health()["malformed_frames"] == 200, 10), svc.health()
    peak = _camera_threads()
    assert _wait(lambda: _camera_threads() == 0 and _os_threads() <= baseline and not svc.health()["cameras"], 15), \
        (baseline, _os_threads(), _camera_threads(), len(svc.health()["cameras"]))
    health = svc.health()
    assert peak >= 100 and health["cameras_closed"] == 200
    assert health["malformed_frames"] == 200 and health["closed_cameras"] == []  # no poses, nothing kept


def test_cap_refuses_new_cameras_until_one_closes(stack) -> None:
    _, client, start_service = stack
    svc = start_service(max_cameras=2, camera_idle_timeout_s=1.0)
    refused = PoseRecorder(client, "cam-c")
    _publish(client, "cam-a", range(3))
    _publish(client, "cam-b", range(3))
    for i in range(20):  # a flood of new ids beyond the cap gets no thread
        client.put(keys.key(f"flood-{i}", "frame"), b"x")
    _publish(client, "cam-c", range(3))
    assert refused.wait_for(lambda r: "camera_refused" in _events(r), 5), refused.statuses
    assert not refused.poses and _camera_threads() == 2
    assert "max_cameras=2" in refused.statuses[-1].event_detail
    # the event goes out with cam-c's first refused frame; its other two may still be in flight
    assert _wait(lambda: svc.health()["refused_frames"] >= 23, 5), svc.health()["refused_frames"]
    assert _wait(lambda: not svc.health()["cameras"], 10)  # a and b idle: closed
    _publish(client, "cam-c", range(3, 6))
    assert refused.wait_frames(3, 10) and sorted(refused.poses) == [3, 4, 5]


def test_idle_camera_is_closed_kept_and_continued(stack) -> None:
    _, client, start_service = stack
    svc = start_service(lambda cid, cam: MovingSession(), camera_idle_timeout_s=0.5)
    recorder = PoseRecorder(client, "cam0")
    _publish(client, "cam0", range(5))
    assert recorder.wait_for(lambda r: "camera_closed" in _events(r), 10), _events(recorder)
    assert svc.health()["cameras"] == [] and svc.health()["closed_cameras"] == ["cam0"]
    closed = query_trajectory(client, "cam0")  # answered after the close
    assert list(closed.frame_index) == list(range(5)) and closed.T_world_cam[-1][2, 3] == 4.0
    # it comes back: a new session continues from z = 4 m, moved on at the camera's last velocity
    # over the gap its timestamps give (frame 5 is 0.1 s after frame 4: 1 m)
    _publish(client, "cam0", range(5, 8))
    assert recorder.wait_frames(8, 10)
    assert recorder.wait_for(lambda r: "session_restarted" in _events(r), 5)
    assert recorder.poses[5].T_world_cam[2, 3] == 5.0 and recorder.poses[7].T_world_cam[2, 3] == 7.0
    assert recorder.poses[5].segment_id == 1
    traj = query_trajectory(client, "cam0")
    assert list(traj.frame_index) == list(range(8))


def test_session_rolls_over_at_max_keyframes(stack) -> None:
    _, client, start_service = stack
    made = []

    def factory(cid, cam):
        made.append(MovingSession())
        return made[-1]

    start_service(factory, max_session_keyframes=10)
    recorder = PoseRecorder(client, "cam0")
    _publish(client, "cam0", range(50))
    assert recorder.wait_frames(50, 10)
    assert recorder.wait_for(lambda r: _events(r).count("session_rolled_over") == 2, 5), _events(recorder)
    assert len(made) == 3 and made[0]._poses and len(made[1]._poses) == 20  # 10 keyframes each
    z = [recorder.poses[i].T_world_cam[2, 3] for i in range(50)]
    assert np.diff(z) == pytest.approx(np.ones(49))  # each seam bridged at the last velocity: 1 m a frame
    assert len(query_trajectory(client, "cam0").frame_index) == 50


def test_restart_continues_from_the_state_directory(stack, tmp_path: Path) -> None:
    _, client, start_service = stack
    svc = start_service(lambda cid, cam: MovingSession(), state_dir=tmp_path)
    recorder = PoseRecorder(client, "cam0")
    _publish(client, "cam0", range(6))
    assert recorder.wait_frames(6, 10)
    svc.stop()
    assert len((tmp_path / "cam0.poses.jsonl").read_text().splitlines()) == 6
    start_service(lambda cid, cam: MovingSession(), state_dir=tmp_path)
    assert list(query_trajectory(client, "cam0").frame_index) == list(range(6))  # from disk
    _publish(client, "cam0", range(6, 9))
    assert recorder.wait_frames(9, 10)
    assert recorder.wait_for(lambda r: "session_restarted" in _events(r), 5)
    # from the last persisted pose (z 5), moved on at its last velocity over the 0.1 s gap; not the origin
    assert recorder.poses[6].T_world_cam[2, 3] == pytest.approx(6.0)
    traj = query_trajectory(client, "cam0")
    assert list(traj.frame_index) == list(range(9))


def test_killed_service_continues_its_cameras(tmp_path: Path) -> None:
    """``metricslam slam-service`` killed with SIGKILL mid-stream, restarted on the same state
    directory: ``…/trajectory`` has the poses from before and ``session_restarted`` is published."""
    endpoint = "tcp/127.0.0.1:17641"
    router = open_router(endpoint)
    client = open_client(endpoint)
    cmd = [sys.executable, "-m", "metricslam_cli.main", "slam-service", "--zenoh-endpoint", endpoint,
           "--session", "identity", "--no-scale", "--depth-url", "none", "--state-dir", str(tmp_path),
           "--status-period", "0.2", "--queue-size", "64"]
    recorder = PoseRecorder(client, "cam0")
    procs = []
    try:
        for run, frames in enumerate((range(0, 10), range(10, 15))):
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            procs.append(proc)
            LineReader(proc).wait("READY", 60)
            assert _wait(lambda: query_health(client, 0.5) is not None, 10)
            time.sleep(1.0)  # until the new service has heard of the recorder's subscriptions
            _publish(client, "cam0", frames)
            assert _wait(lambda n=frames.stop: len(_trajectory_or_none(client)) == n, 20), sorted(recorder.poses)
            if run == 0:
                proc.kill()  # no clean shutdown: only the appended lines survive
                proc.wait(10)
        assert recorder.wait_for(lambda r: "session_restarted" in _events(r), 5)
        traj = query_trajectory(client, "cam0")
        assert list(traj.frame_index) == list(range(15))
    finally:
        for proc in procs:
            interrupt_and_wait(proc)
        client.close()
        router.close()


def test_the_status_thread_trims_the_heap_every_period_only_when_asked(stack, monkeypatch) -> None:
    """``SLAM_HEAP_TRIM_PERIOD_S`` (default 10 s): the status thread returns free heap pages that
    often; 0 leaves trimming to session closes."""
    from metricslam_slam.service import slam_service

    calls: list[float] = []
    monkeypatch.setattr(slam_service, "trim_heap", lambda: calls.append(time.monotonic()))
    assert SlamServiceSettings().heap_trim_period_s == 10.0
    _, _, start_service = stack
    svc = start_service(heap_trim_period_s=0)
    time.sleep(0.6)  # six status periods
    assert calls == []
    svc.stop()
    start_service(heap_trim_period_s=0.3)
    assert _wait(lambda: len(calls) >= 3, 5.0), calls
    assert min(b - a for a, b in zip(calls, calls[1:])) >= 0.25  # the period, not every status tick


class _SessionWithGraphEvents(IdentitySession):
    """Identity poses, and the event bus a real session's global back end has."""

    def __init__(self) -> None:
        super().__init__()
        self.backend = SimpleNamespace(events=EventBus())


def _factory_into(sessions: list) -> object:
    def factory(camera_id: str, camera: PinholeCamera) -> _SessionWithGraphEvents:
        sessions.append(_SessionWithGraphEvents())
        return sessions[-1]
    return factory


def test_a_batch_re_solve_of_the_global_graph_trims_the_heap_at_once(stack, monkeypatch) -> None:
    """Each accepted loop replaces the graph's ISAM2 (``Solved.batch``): its memory goes back to
    the OS right then, not at the next periodic trim; incremental solves trim nothing, and with
    ``SLAM_HEAP_TRIM_PERIOD_S=0`` (no trimming asked for) neither does a batch one."""
    from metricslam_slam.service import slam_service

    calls: list[float] = []
    monkeypatch.setattr(slam_service, "trim_heap", lambda: calls.append(time.monotonic()))
    _, client, start_service = stack
    for period, expected in ((1000.0, 1), (0.0, 0)):  # 1000 s: no periodic trim within the test
        sessions: list[_SessionWithGraphEvents] = []
        svc = start_service(_factory_into(sessions), heap_trim_period_s=period)
        _publish(client, "cam0", range(2))
        assert _wait(sessions.__len__, 5.0)
        calls.clear()
        bus = sessions[0].backend.events
        bus.emit(Solved(10, 10, 12, 0, 1.0, batch=False))
        assert calls == []
        bus.emit(Solved(11, 11, 13, 0, 80.0, batch=True))
        assert len(calls) == expected, (period, calls)
        svc.stop()


class AliasedSession(MovingSession):
    """:class:`MovingSession` whose VO reports frames 3-5 and 9 as suspect (tracks possibly aliased)."""

    def process(self, frame):
        pose = super().process(frame)
        return dataclasses.replace(pose, vo_suspect=frame.index in (3, 4, 5, 9))


def test_suspect_vo_frames_give_one_status_event_per_run(stack) -> None:
    _, client, start_service = stack
    start_service(lambda cid, cam: AliasedSession())
    recorder = PoseRecorder(client, "cam0")
    _publish(client, "cam0", range(12))
    assert recorder.wait_frames(12, 10)
    assert recorder.wait_for(lambda r: _events(r).count("vo_suspect") == 2, 5), _events(recorder)
    details = [s.event_detail for s in recorder.statuses if s.event == "vo_suspect"]
    assert details[0].startswith("frame 3:") and details[1].startswith("frame 9:"), details
    assert "aliased" in details[0]
