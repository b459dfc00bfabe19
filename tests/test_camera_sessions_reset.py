"""Issue #32 items 1 and 4 over a real SLAM service and real zenoh sessions on loopback.

1. A camera id's trajectory is continued only while its frames go on: a second replay under the
   same id (frame index / timestamp going back), against a running service, after an idle close
   or across a restart on the same state directory, starts a new session at the origin, and the
   log, the status topic, ``poses`` and ``replay`` say so and why; ``replay --new-session`` (the
   ``metricslam/_service/reset/<camera_id>`` queryable) starts one whatever the frames.
4. When the SLAM service restarts mid-replay, ``replay`` and ``poses`` name the restart, not the
   replay rate.

The sessions are :class:`MovingSession` (1 m along z a frame from their own origin), so "where
did frame 0 of the second run land" is the z of its pose.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from metricslam.camera import PinholeCamera
from metricslam.errors import ServiceError
from metricslam.slam.system_config import SystemConfig
from metricslam.slam.types import PoseEstimate, TrackingState
from metricslam.trajectory.io import read_kitti_poses
from metricslam.wire import keys
from metricslam.wire.codec import decode_as
from metricslam.wire.odometry_message import OdometryMessage
from metricslam_cli.main import main
from metricslam_slam.service.sessions import IdentitySession
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.slam_service import SlamService
from metricslam_slam.supervisor.launcher import free_port
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import FramePublisher, PoseRecorder, query_health, query_trajectory
from metricslam_slam.zenoh_config import open_client

CAMERA = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=31.5, cy_px=23.5, width_px=64, height_px=48)
IMAGE = np.full((48, 64), 7, dtype=np.uint8)
N_FRAMES = 8  # of the replayed folder


class MovingSession(IdentitySession):
    """Moves 1 m along z per frame from its own origin; ``final_x_m``: its close (the pipeline's
    marginalized window and final solve) moves every pose that far along x."""

    def __init__(self, delay_s: float = 0.0, final_x_m: float = 0.0) -> None:
        super().__init__()
        self.delay_s, self.final_x_m = delay_s, final_x_m

    def close(self) -> None:
        for pose in self._poses:
            pose.T_world_cam[0, 3] += self.final_x_m

    def process(self, frame):
        if self.delay_s:
            time.sleep(self.delay_s)
        T = np.eye(4)
        T[2, 3] = float(len(self._poses))
        pose = PoseEstimate(frame.index, frame.t_ns, T, TrackingState.TRACKING)
        self._poses.append(pose)
        return pose


@pytest.fixture()
def stack():
    """(endpoint, client session, start_service(**settings), services started)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    client = open_client(endpoint)
    services: list[SlamService] = []

    def start_service(delay_s: float = 0.0, final_x_m: float = 0.0, **overrides) -> SlamService:
        settings = SlamServiceSettings(**{"zenoh_endpoint": endpoint, "depth_url": None, "session_kind": "identity",
                                          "status_period_s": 0.1, **overrides})
        svc = SlamService(settings, session_factory=lambda cid, cam: MovingSession(delay_s, final_x_m),
                          config=SystemConfig(depth={"use_scale": False}, queues={"frames": 64})).start()
        services.append(svc)
        deadline = time.monotonic() + 5  # until this service (not one stopped before) answers
        while time.monotonic() < deadline:
            health = query_health(client, 0.5)
            if health is not None and health.get("instance") == getattr(svc, "instance", None):
                break
            time.sleep(0.05)
        return svc

    yield endpoint, client, start_service, services
    for svc in services:
        svc.stop()
    client.close()
    router.close()


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """A KITTI-layout folder of N_FRAMES 32x24 frames at 10 Hz."""
    root = tmp_path_factory.mktemp("sessions") / "seq"
    (root / "image_0").mkdir(parents=True)
    for i in range(N_FRAMES):
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), np.full((24, 32), 10 * i, np.uint8))
    p0 = "50 0 15.5 0 0 50 11.5 0 0 0 1 0"
    (root / "calib.txt").write_text(f"P0: {p0}\nP1: {p0}\n")
    (root / "times.txt").write_text("".join(f"{i / 10:.6e}\n" for i in range(N_FRAMES)))
    return root


def _publish(client, indices, camera_id: str = "cam0") -> None:
    pub = FramePublisher(client, camera_id)
    assert pub.wait_for_subscriber(10), "no SLAM service subscribed to the frames"
    for i in indices:
        pub.publish(i, i * 100_000_000, IMAGE, CAMERA)
    pub.close()


def _wait(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def _details(recorder: PoseRecorder, event: str = "session_restarted") -> list[str]:
    return [s.event_detail for s in list(recorder.statuses) if s.event == event]


def _run_cli(argv: list[str], into: dict) -> threading.Thread:
    thread = threading.Thread(target=lambda: into.__setitem__(argv[0], main(argv)), daemon=True)
    thread.start()
    return thread


# -- item 1: the service --------------------------------------------------------------------
def test_a_second_run_against_a_running_service_starts_a_new_session(stack, caplog) -> None:
    _, client, start_service, _ = stack
    start_service()
    first = PoseRecorder(client, "cam0")
    _publish(client, range(6))
    assert first.wait_frames(6, 10) and first.poses[5].T_world_cam[2, 3] == 5.0
    second = PoseRecorder(client, "cam0")
    odom: list[OdometryMessage] = []
    sub = client.declare_subscriber(keys.key("cam0", "odom"),
                                    lambda s: odom.append(decode_as(s.payload.to_bytes(), OdometryMessage)))
    with caplog.at_level(logging.WARNING, logger="metricslam_slam.service.camera_worker"):
        _publish(client, range(4))
        assert second.wait_frames(4, 10)
        assert second.wait_for(lambda r: _details(r), 5)
        assert _wait(lambda: len(odom) >= 4, 5)
    sub.undeclare()
    # frame 0 of the second run is at the origin of a fresh session, not after z = 5 m
    assert [second.poses[i].T_world_cam[2, 3] for i in range(4)] == [0.0, 1.0, 2.0, 3.0]
    # ... and so is the continuous odometry: it starts over, it does not blend back from z = 5 m
    assert [m.T_world_cam[2, 3] for m in odom[-4:]] == [0.0, 1.0, 2.0, 3.0]
    detail = _details(second)[-1]
    assert detail.startswith("new session") and "frame index went back from 5 to 0" in detail, detail
    assert "earlier trajectory (6 poses, to frame 5) is not continued" in detail, detail
    assert any("new session" in r.getMessage() and "went back from 5 to 0" in r.getMessage()
               for r in caplog.records), [r.getMessage() for r in caplog.records]
    traj = query_trajectory(client, "cam0")  # the new session's only
    assert list(traj.frame_index) == [0, 1, 2, 3] and traj.T_world_cam[0][2, 3] == 0.0


def test_a_timestamp_going_back_starts_a_new_session_and_may_bring_new_intrinsics(stack) -> None:
    _, client, start_service, _ = stack
    svc = start_service()
    recorder = PoseRecorder(client, "cam0")
    _publish(client, range(3))
    assert recorder.wait_frames(3, 10)
    other = PinholeCamera(fx_px=80.0, fy_px=80.0, cx_px=31.5, cy_px=23.5, width_px=64, height_px=48)
    pub = FramePublisher(client, "cam0")
    assert pub.wait_for_subscriber(10)
    pub.publish(3, 0, IMAGE, other)  # index goes on, time goes back, another camera
    pub.publish(4, 100_000_000, IMAGE, other)
    pub.close()
    assert recorder.wait_frames(5, 10)
    assert recorder.poses[3].T_world_cam[2, 3] == 0.0 and recorder.poses[4].T_world_cam[2, 3] == 1.0
    assert recorder.wait_for(lambda r: any("timestamp went back" in d for d in _details(r)), 5), _details(recorder)
    assert svc.health()["malformed_frames"] == 0  # the new intrinsics were not refused


def test_an_idle_closed_camera_replayed_from_frame_0_is_not_continued(stack) -> None:
    _, client, start_service, _ = stack
    start_service(camera_idle_timeout_s=0.5)
    recorder = PoseRecorder(client, "cam0")
    _publish(client, range(5))
    assert recorder.wait_for(lambda r: _details(r, "camera_closed"), 10)
    second = PoseRecorder(client, "cam0")
    _publish(client, range(3))
    assert second.wait_frames(3, 10)
    assert second.poses[0].T_world_cam[2, 3] == 0.0 and second.poses[0].segment_id == 0
    assert second.wait_for(lambda r: any(d.startswith("new session") for d in _details(r)), 5), _details(second)
    assert list(query_trajectory(client, "cam0").frame_index) == [0, 1, 2]


def test_a_restarted_service_does_not_continue_a_run_that_starts_over(stack, tmp_path: Path) -> None:
    """``SLAM_STATE_DIR`` (compose and k8s set it): before, the second run's frame 0 was placed
    after the persisted frame 5 ("continuing from frame 5")."""
    _, client, start_service, _ = stack
    svc = start_service(state_dir=tmp_path)
    recorder = PoseRecorder(client, "cam0")
    _publish(client, range(6))
    assert recorder.wait_frames(6, 10)
    svc.stop()
    start_service(state_dir=tmp_path)
    second = PoseRecorder(client, "cam0")
    _publish(client, range(3))
    assert second.wait_frames(3, 10)
    assert second.poses[0].T_world_cam[2, 3] == 0.0
    assert second.wait_for(lambda r: _details(r), 5)
    detail = _details(second)[-1]
    assert detail.startswith("new session") and "went back from 5 to 0" in detail, detail
    assert list(query_trajectory(client, "cam0").frame_index) == [0, 1, 2]
    assert len((tmp_path / "cam0.poses.previous.jsonl").read_text().splitlines()) == 6  # set aside, not lost
    assert _wait(lambda: len((tmp_path / "cam0.poses.jsonl").read_text().splitlines()) == 3, 5)


@pytest.mark.parametrize("idle_closed", [False, True])
def test_a_reset_starts_a_new_session_whatever_the_frames(stack, tmp_path: Path, idle_closed: bool) -> None:
    from metricslam_slam.tools.client import reset_camera

    _, client, start_service, _ = stack
    start_service(state_dir=tmp_path, camera_idle_timeout_s=0.5 if idle_closed else 60.0)
    recorder = PoseRecorder(client, "cam0")
    _publish(client, range(5))
    assert recorder.wait_frames(5, 10)
    if idle_closed:
        assert recorder.wait_for(lambda r: _details(r, "camera_closed"), 10)
    answer = reset_camera(client, "cam0", "a test")
    assert answer["earlier_poses"] == 5
    _publish(client, range(5, 8))  # frames that go on: continued without the reset
    assert recorder.wait_frames(8, 10)
    assert [recorder.poses[i].T_world_cam[2, 3] for i in (5, 6, 7)] == [0.0, 1.0, 2.0]
    assert recorder.wait_for(lambda r: any("reset requested (a test)" in d for d in _details(r)), 5), \
        _details(recorder)
    assert list(query_trajectory(client, "cam0").frame_index) == [5, 6, 7]


def test_a_reset_nobody_answers_is_an_error(stack) -> None:
    from metricslam_slam.tools.client import reset_camera

    _, client, _, _ = stack
    with pytest.raises(ServiceError, match="could not reset camera 'cam0'.*metricslam up"):
        reset_camera(client, "cam0", timeout_s=1.0)


def test_the_tools_read_new_sessions_as_the_service_writes_them() -> None:
    from metricslam_slam.service import camera_worker
    from metricslam_slam.service.continued_session import why_new_session
    from metricslam_slam.tools import client as client_tools

    assert client_tools.NEW_SESSION == camera_worker.NEW_SESSION
    assert why_new_session(5, 500, 6, 500) is None and "sent again" in why_new_session(5, 500, 5, 600)


# -- item 1: the documented poses + replay pair, twice ----------------------------------------
def test_finish_closes_the_camera_and_poses_writes_its_final_trajectory(stack, tmp_path: Path, capsys) -> None:
    """``poses --trajectory --finish`` (the ``…/_service/finish/<camera_id>`` queryable): the
    answer is the closed session's trajectory (after its final solve), not the open one's."""
    from metricslam_slam.tools.client import finish_camera

    endpoint, client, start_service, _ = stack
    svc = start_service(final_x_m=5.0)
    recorder = PoseRecorder(client, "cam0")
    _publish(client, range(4))
    assert recorder.wait_frames(4, 10)
    assert {T[0, 3] for T in query_trajectory(client, "cam0").T_world_cam} == {0.0}  # open: not final
    est = tmp_path / "final.txt"
    assert main(["poses", "--zenoh-endpoint", endpoint, "--out", str(est), "--timeout", "0.5",
                 "--trajectory", "--finish", "--all"]) == 0
    final = read_kitti_poses(est)
    assert len(final) == 4 and {T[0, 3] for T in final} == {5.0} and final[3][2, 3] == 3.0
    health = svc.health()
    assert health["cameras"] == [] and health["closed_cameras"] == ["cam0"]
    assert recorder.wait_for(lambda r: any(d.startswith("finish requested (metricslam poses")
                                           for d in _details(r, "camera_closed")), 5), _details(recorder, "camera_closed")
    assert finish_camera(client, "cam0")["finished"] is False  # nothing running any more
    _publish(client, range(4, 6))  # frames that go on are continued from the final pose
    assert recorder.wait_frames(6, 10) and recorder.poses[4].T_world_cam[2, 3] == 4.0
    capsys.readouterr()
    assert main(["poses", "--zenoh-endpoint", endpoint, "--out", str(est), "--finish"]) == 1
    assert "--finish" in capsys.readouterr().err


def test_the_documented_poses_and_replay_pair_twice(stack, folder: Path, tmp_path: Path, capsys) -> None:
    endpoint, _, start_service, _ = stack
    start_service()
    z_first = {}
    for run, extra in ((1, []), (2, []), (3, ["--new-session"])):
        est = tmp_path / f"est{run}.txt"
        codes: dict = {}
        poses = _run_cli(["poses", "--zenoh-endpoint", endpoint, "--out", str(est), "--frames", str(N_FRAMES),
                          "--timeout", "30", "--all"], codes)
        time.sleep(1.0)  # the recorder subscribes before the first frame
        assert main(["replay", str(folder), "--zenoh-endpoint", endpoint, "--rate", "0", "--no-progress",
                     "--confirm-timeout", "2", "--wait", "10", *extra]) == 0
        poses.join(60)
        out = capsys.readouterr().out
        assert codes.get("poses") == 0, out
        z_first[run] = read_kitti_poses(est)[0][2, 3]
        said = [line for line in out.splitlines() if line.startswith("the SLAM service started a new session")]
        sent = [line for line in out.splitlines() if line.startswith("sent ")]
        if run == 1:
            assert not said, out
        else:
            why = "frame index went back from 7 to 0" if run == 2 else "reset requested (metricslam replay --new-session)"
            assert len(said) == 1 and why in said[0] and "(camera cam0)" in said[0], out  # poses' output
            assert len(sent) == 1 and "new session" in sent[0] and why in sent[0], out  # replay's output
    assert z_first == {1: 0.0, 2: 0.0, 3: 0.0}  # before: run 2 began at z = 8 m, run 3 at 16 m


# -- item 4: a restart mid-replay is named as such -------------------------------------------
def test_replay_and_poses_name_a_restart_of_the_service(stack, folder: Path, tmp_path: Path, capsys) -> None:
    endpoint, client, start_service, services = stack
    start_service(delay_s=0.05)
    codes: dict = {}
    poses = _run_cli(["poses", "--zenoh-endpoint", endpoint, "--out", str(tmp_path / "est.txt"), "--frames",
                      str(4 * N_FRAMES), "--timeout", "12", "--all"], codes)
    time.sleep(1.0)
    long_folder = tmp_path / "long"  # the same frames four times over, 4 s at 8 Hz
    (long_folder / "image_0").mkdir(parents=True)
    for i in range(4 * N_FRAMES):
        (long_folder / "image_0" / f"{i:06d}.png").write_bytes((folder / "image_0" / f"{i % N_FRAMES:06d}.png").read_bytes())
    (long_folder / "calib.txt").write_text((folder / "calib.txt").read_text())
    (long_folder / "times.txt").write_text("".join(f"{i / 10:.6e}\n" for i in range(4 * N_FRAMES)))
    replay = _run_cli(["replay", str(long_folder), "--zenoh-endpoint", endpoint, "--rate", "8", "--no-progress",
                       "--confirm-timeout", "2", "--wait", "10"], codes)
    time.sleep(1.5)
    services[0].stop()  # the service goes away mid-replay (as a crash would) ...
    time.sleep(1.0)
    start_service(delay_s=0.05)  # ... and is started again, as `metricslam up` does
    replay.join(60)
    poses.join(60)
    captured = capsys.readouterr()
    errors = captured.err.splitlines()
    replay_error = next((e for e in errors if e.startswith("metricslam replay: error:")), "")
    poses_error = next((e for e in errors if e.startswith("metricslam poses: error:")), "")
    assert codes == {"replay": 1, "poses": 1}, captured
    for error in (replay_error, poses_error):
        assert "restarted during the" in error and "new instance" in error, captured
        assert "lower --rate" not in error and "dropped from a full queue" not in error, error
    assert "the SLAM service restarted during the recording" in captured.out, captured.out
