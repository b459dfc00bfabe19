"""End-to-end with real processes on loopback: ``up`` + ``replay`` + ``poses`` on a synthetic
sequence; the depth service is killed mid-run (poses keep flowing, status says so) and comes
back (supervised restart; scale factors resume). Nothing is mocked."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from metricslam.datasets import open_sequence
from metricslam.depth import RENDERED_MODEL_PATH
from metricslam.trajectory.io import read_kitti_poses
from metricslam_slam.tools.client import PoseRecorder, query_trajectory
from metricslam_slam.tools.replay import replay_sequence
from metricslam_slam.zenoh_config import open_client

from child_process import interrupt_and_wait

ENDPOINT = "tcp/127.0.0.1:17450"
DEPTH_PORT = 18250
N_FRAMES = 56
OUTAGE_FRAMES = 8  # frames replayed while the depth service is dead
# Path-length scale error of the optimized trajectory vs ground truth. 56 frames (~45 m) with a
# depth outage in the middle; the interim shipped model gives ~9 % offline (`metricslam run`) and
# ~15 % live on this sequence; a non-metric model gives ~90 %.
SCALE_TOL_PCT = 20.0


def _path_length_m(T: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).sum())
CLI = [sys.executable, "-m", "metricslam_cli.main"]


@pytest.fixture(scope="module")
def synth_seq(tmp_path_factory) -> Path:
    from metricslam.synth import generate_sequence

    out = tmp_path_factory.mktemp("e2e") / "seq"
    generate_sequence(out, frames=N_FRAMES, seed=5, path="turns")  # KITTI size: enough keyframes
    return out


class _Lines:
    """Reads a child's stdout lines on a thread so the test can wait for one with a timeout."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.q: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._pump, args=(proc,), daemon=True).start()

    def _pump(self, proc) -> None:
        for line in proc.stdout:
            self.q.put(line)

    def wait(self, prefix: str, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self.q.get(timeout=0.5)
            except queue.Empty:
                continue
            self.seen.append(line)
            if line.startswith(prefix):
                return line
        raise AssertionError(f"no line starting with {prefix!r} in {timeout_s} s; got {self.seen}")


def _stop(proc: subprocess.Popen) -> None:
    interrupt_and_wait(proc)


@pytest.mark.slow
def test_up_replay_poses_with_depth_outage(synth_seq: Path, tmp_path: Path) -> None:
    # the depth service reads the rendered world with the model for rendered worlds (the shipped
    # default is trained on real streets only); DEPTH_MODEL_PATH is how an operator names it
    env = dict(os.environ, PYTHONUNBUFFERED="1", DEPTH_MODEL_PATH=str(RENDERED_MODEL_PATH))
    up = subprocess.Popen(CLI + ["up", "--zenoh-endpoint", ENDPOINT, "--depth-port", str(DEPTH_PORT),
                                 "--log-dir", str(tmp_path / "logs"), "--restart-delay", "3"],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    lines = _Lines(up)
    procs = [up]
    session = None
    try:
        depth_pid = int(lines.wait("depth-service", 90).split("pid")[1].split()[0])
        lines.wait("UP:", 90)
        session = open_client(ENDPOINT)
        watch = PoseRecorder(session, "cam0")
        est = tmp_path / "est.txt"
        poses = subprocess.Popen(CLI + ["poses", "--zenoh-endpoint", ENDPOINT, "--out", str(est),
                                        "--frames", str(N_FRAMES), "--timeout", "150"],
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        procs.append(poses)
        _Lines(poses).wait("recording", 30)
        def replay(first: int, count: int) -> None:
            out = subprocess.run(CLI + ["replay", str(synth_seq), "--zenoh-endpoint", ENDPOINT,
                                        "--rate", "10", "--max-in-flight", "3", "--no-progress",
                                        "--start", str(first), "--max-frames", str(count)],
                                 capture_output=True, text=True, env=env, timeout=120)
            assert out.returncode == 0, out.stdout + out.stderr

        def scale_factors(r: PoseRecorder) -> int:
            status = r.latest_status()
            return 0 if status is None else status.session_stats.get("backend.scale_factors", 0)

        # 1. depth up: replay until the first scale factors are in (keyframes are marginalized
        #    only once the local window is full, so the count of frames needed varies).
        client_replay = open_client(ENDPOINT)
        seq = open_sequence(synth_seq)
        k = 0
        while scale_factors(watch) == 0 and k < N_FRAMES - OUTAGE_FRAMES - 12:
            replay_sequence(client_replay, seq, "cam0", 10.0, k, k + 4, max_in_flight=3, progress=False)
            k += 4
            watch.wait_for(lambda r: scale_factors(r) > 0, 2.0)
        assert watch.wait_for(lambda r: scale_factors(r) > 0, 30), {
            k: v for k, v in watch.latest_status().session_stats.items() if "ms_" not in k}
        # 2. depth killed: status says so, poses keep flowing.
        os.kill(depth_pid, signal.SIGKILL)
        assert watch.wait_for(lambda r: r.latest_status().depth_reachable is False, 15)
        assert watch.latest_status().depth_error
        replay_sequence(client_replay, seq, "cam0", 10.0, k, k + OUTAGE_FRAMES, max_in_flight=3, progress=False)
        client_replay.close()
        k += OUTAGE_FRAMES
        assert watch.wait_for(lambda r: len(r.poses) >= k, 60), sorted(watch.poses)
        # 3. the launcher restarts it: status recovers; the rest goes through the replay CLI
        #    and new scale factors arrive.
        lines.wait("depth-service  restarted", 30)
        assert watch.wait_for(lambda r: r.latest_status().depth_reachable is True, 60)
        factors_down = scale_factors(watch)
        replay(k, N_FRAMES - k)
        assert poses.wait(120) == 0, poses.stdout.read()
        assert watch.wait_for(lambda r: scale_factors(r) > factors_down, 30), "scale factors did not resume"

        T = read_kitti_poses(est)
        assert T.shape == (N_FRAMES, 4, 4) and np.all(np.isfinite(T))
        assert sorted(watch.poses) == list(range(N_FRAMES))  # every frame has a pose
        final = watch.latest_status()
        assert final.queue_drops == 0 and final.malformed == 0
        assert final.scale_established
        optimized = query_trajectory(session, "cam0")
        watch.close()
    finally:
        if session is not None:
            session.close()
        for proc in reversed(procs):
            _stop(proc)
    assert up.returncode == 0

    # Metric: the optimized trajectory's travelled distance vs ground truth (any path shape).
    T_gt = open_sequence(synth_seq).T_world_cam_gt
    scale_error_pct = 100 * abs(_path_length_m(optimized.T_world_cam) / _path_length_m(T_gt) - 1)
    assert scale_error_pct <= SCALE_TOL_PCT, f"scale error {scale_error_pct:.1f} %"


def test_children_die_with_a_killed_launcher(tmp_path: Path) -> None:
    """SIGKILL on `up` (no chance to clean up): its children still go (PR_SET_PDEATHSIG)."""
    up = subprocess.Popen(CLI + ["up", "--zenoh-endpoint", "tcp/127.0.0.1:17455", "--no-scale",
                                 "--session", "identity"],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
    lines = _Lines(up)
    try:
        pids = [int(lines.wait(name, 60).split("pid")[1].split()[0])
                for name in ("zenoh-router", "slam-service")]
        lines.wait("UP:", 30)
    finally:
        up.kill()
        up.wait()
    deadline = time.monotonic() + 20
    alive = pids
    while alive and time.monotonic() < deadline:
        time.sleep(0.2)
        alive = [pid for pid in pids if Path(f"/proc/{pid}").exists()
                 and "Z" not in Path(f"/proc/{pid}/stat").read_text().split()[2]]
    for pid in alive:  # do not leak processes when the check fails
        os.kill(pid, signal.SIGKILL)
    assert not alive, f"children still running after the launcher was killed: {alive}"
