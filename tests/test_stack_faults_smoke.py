"""Issue #19: the SLAM service killed with SIGKILL under ``metricslam up`` during a replay.

``replay`` reports the frames it lost (exit code 1, the counts), the supervisor restarts the
service, and the restarted service continues the camera from its state directory as a new
linked segment: ``session_restarted`` on the status key, ``…/trajectory`` holds the frames from
before the kill and after the restart, and the new segment starts at the last persisted pose.
``up`` is run as the README recipe runs it, without ``SLAM_STATE_DIR``: it gives the SLAM service
a temporary state directory of its own (before, a restarted SLAM service started the camera over
at the origin and ``…/trajectory`` forgot everything from before the kill).
Transport-only sessions (``--session identity --no-scale``) keep it fast; the real stack, every
child and SIGSTOP too, was measured by the retired ``bench/stack_faults.py``
(``bench/results/stack_faults.md``). Ports are free ephemeral ones, never the defaults.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from metricslam_slam.supervisor.launcher import Stack, free_port
from metricslam_slam.tools.client import PoseRecorder, query_trajectory
from metricslam_slam.zenoh_config import open_client

from child_process import LineReader, interrupt_and_wait

CLI = [sys.executable, "-m", "metricslam_cli.main"]
N_FRAMES = 300
RATE_HZ = 40  # 7.5 s of frames: the service is killed after 20, restarted within a few seconds


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    root = tmp_path / "seq"
    (root / "image_0").mkdir(parents=True)
    for i in range(N_FRAMES):
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), np.full((24, 32), i % 256, np.uint8))
    p0 = "50 0 15.5 0 0 50 11.5 0 0 0 1 0"
    (root / "calib.txt").write_text(f"P0: {p0}\nP1: {p0}\n")
    (root / "times.txt").write_text("".join(f"{i / RATE_HZ:.6e}\n" for i in range(N_FRAMES)))
    return root


@pytest.mark.timeout(90)
def test_killed_slam_service_loss_is_reported_and_the_camera_continues(tmp_path: Path, folder: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("SLAM_STATE_DIR", None)
    up = subprocess.Popen(CLI + ["up", "--zenoh-endpoint", endpoint, "--no-scale", "--session", "identity",
                                 "--restart-delay", "0.2", "--log-dir", str(tmp_path / "logs")],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    lines = LineReader(up)
    session = replay = None
    try:
        ready = lines.wait("slam-service", 60)
        slam_pid = int(ready.split("pid")[1].split()[0])
        state_dir = Path(ready.split("state in")[1].strip())
        assert state_dir.is_dir() and state_dir.name.startswith("metricslam-up-state-")
        lines.wait("UP:", 30)
        session = open_client(endpoint)
        recorder = PoseRecorder(session, "cam0")
        replay = subprocess.Popen(CLI + ["replay", str(folder), "--zenoh-endpoint", endpoint, "--rate",
                                         str(RATE_HZ), "--no-progress", "--confirm-timeout", "3"],
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        assert recorder.wait_frames(20, 30), sorted(recorder.poses)
        os.kill(slam_pid, signal.SIGKILL)
        lines.wait("slam-service   restarted", 20)
        out = replay.communicate(timeout=60)[0]

        assert replay.returncode == 1, out  # frames were lost: not a success
        sent = int(re.search(r"sent (\d+) frames", out).group(1))
        confirmed = int(re.search(r"confirmed (\d+)", out).group(1))
        lost = int(re.search(r"; (\d+) without a pose", out).group(1))
        assert sent == N_FRAMES and lost == sent - confirmed > 0, out
        assert len(recorder.poses) == confirmed  # what replay counted is what was published
        assert recorder.wait_for(lambda r: any(s.event == "session_restarted" for s in r.statuses), 10)

        frames = [int(i) for i in query_trajectory(session, "cam0").frame_index]
        before = sorted(i for i, p in recorder.poses.items() if p.segment_id == 0)
        after = sorted(i for i, p in recorder.poses.items() if p.segment_id >= 1)
        last_before = before[-1]
        assert before == list(range(last_before + 1))  # nothing lost before the kill
        assert after and after[0] > last_before + 1  # a new segment, after the frames lost
        assert set(range(last_before + 1)) <= set(frames)  # every pose from before the kill ...
        assert set(after) <= set(frames)  # ... and after the restart
        assert np.allclose(recorder.poses[after[0]].T_world_cam, recorder.poses[last_before].T_world_cam)
        recorder.close()
    finally:
        if replay is not None and replay.poll() is None:
            replay.kill()
            replay.wait()
        if session is not None:
            session.close()
        interrupt_and_wait(up)
    assert up.returncode == 0
    assert not state_dir.exists()  # up's own state directory goes with it


def test_up_gives_the_slam_service_its_state_dir() -> None:
    stack = Stack(f"tcp/127.0.0.1:{free_port()}", depth_port=None, state_dir="/srv/state")
    argv = stack.children[-1].argv
    assert argv[argv.index("--state-dir") + 1] == "/srv/state"
    assert "--state-dir" not in Stack(f"tcp/127.0.0.1:{free_port()}", depth_port=None).children[-1].argv
