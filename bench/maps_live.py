"""KITTI raw 0013 session 2 through the live stack with a saved map (issue #34's live target).

``metricslam up --map MAP`` (router, depth service, SLAM service as supervised processes on
loopback), ``metricslam poses --trajectory`` recording, ``metricslam replay`` of session 2
(frames 40-143, renumbered) at 10 Hz with back-pressure (``--max-in-flight 3``: no frame is
dropped, so the replay runs as fast as the stack keeps up). Reported like the offline session
(:func:`bench.maps.kitti_raw_0013`): the first map-frame frame, its overlap with session 1's
map-frame positions (frames 40-99, no alignment) in % of the GPS/INS path, ATE SE(3) against the
truth, the ``relocalized`` status event. Called by ``python -m bench.maps --live``.
"""

from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
from bench.accuracy import METRICSLAM as CLI
from metricslam.trajectory.io import read_kitti_poses


def _lines(proc: subprocess.Popen) -> queue.Queue:
    q: queue.Queue = queue.Queue()

    def pump() -> None:
        for line in proc.stdout:
            q.put(line.rstrip("\n"))
        q.put(None)

    threading.Thread(target=pump, daemon=True).start()
    return q


def _wait_line(q: queue.Queue, prefix: str, timeout_s: float, seen: list[str]) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            line = q.get(timeout=max(deadline - time.monotonic(), 0.01))
        except queue.Empty:
            break
        if line is None:
            break
        seen.append(line)
        if prefix in line:
            return line
    raise RuntimeError(f"no line with {prefix!r} within {timeout_s:g} s; last lines: {seen[-5:]}")


def live_0013(work: Path, map_dir: Path, s2: Path, s1_est: Path, gt: np.ndarray, ate) -> dict:
    """The live run (module docstring); ``ate(est, gt)``: ATE SE(3) in m."""
    from metricslam_slam.supervisor.launcher import free_port
    from metricslam_slam.tools.client import PoseRecorder
    from metricslam_slam.zenoh_config import open_client

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    up = subprocess.Popen(CLI + ["up", "--zenoh-endpoint", endpoint, "--depth-port", str(free_port()),
                                 "--preset", "kitti", "--map", str(map_dir), "--log-dir", str(work / "live_logs")],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    seen: list[str] = []
    q = _lines(up)
    est = work / "k13_live.txt"
    try:
        _wait_line(q, "UP:", 180, seen)
        client = open_client(endpoint)
        recorder = PoseRecorder(client, "cam0")
        poses = subprocess.Popen(CLI + ["poses", "--zenoh-endpoint", endpoint, "--out", str(est), "--frames", "104",
                                        "--timeout", "900", "--trajectory"],
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        pq, pseen = _lines(poses), []
        _wait_line(pq, "recording", 60, pseen)
        time.sleep(1.0)
        t0 = time.monotonic()
        replay = subprocess.run(CLI + ["replay", str(s2), "--zenoh-endpoint", endpoint, "--rate", "10",
                                       "--max-in-flight", "3", "--no-progress"],
                                capture_output=True, text=True, env=env, timeout=900)
        replay_s = time.monotonic() - t0
        code = poses.wait(960)
        while (line := pq.get(timeout=5)) is not None:
            pseen.append(line)
        statuses = recorder.statuses_so_far()
        live_frames = {i: p.frame_id for i, p in recorder.poses.items()}
        live_T = {i: p.T_world_cam for i, p in recorder.poses.items() if p.frame_id == "map"}
        recorder.close()
        client.close()
    finally:
        up.send_signal(signal.SIGINT)
        try:
            up.wait(60)
        except subprocess.TimeoutExpired:
            up.kill()
    printed = "\n".join(pseen)
    found = re.search(r"poses in the map frame from frame (\d+) on", printed)
    out = {"poses_exit_code": code, "replay_exit_code": replay.returncode, "replay_s": replay_s,
           "relocalized_events": [s.event_detail for s in statuses if s.event == "relocalized"],
           "live_first_map_frame": min((i for i, f in live_frames.items() if f == "map"), default=None),
           "trajectory_first_map_frame": int(found.group(1)) if found else None}
    if found:
        f0 = out["trajectory_first_map_frame"]
        e1, e2 = read_kitti_poses(s1_est), read_kitti_poses(est)
        frames = np.arange(40 + f0, 40 + f0 + len(e2))
        overlap = frames[frames < 100]
        d = np.linalg.norm(e2[:len(overlap), :3, 3] - e1[overlap, :3, 3], axis=1)
        path = float(np.sum(np.linalg.norm(np.diff(gt[overlap, :3, 3], axis=0), axis=1)))
        out.update({"overlap_frames": f"{int(overlap[0])}-{int(overlap[-1])}",
                    "overlap_vs_session1_rmse_pct_of_path": 100 * float(np.sqrt(np.mean(d ** 2))) / path,
                    "overlap_vs_session1_max_pct_of_path": 100 * float(d.max()) / path,
                    "ate_se3_live_trajectory_m": ate(e2, gt[frames]), "ate_frames": f"{int(frames[0])}-{int(frames[-1])}"})
    if live_T:  # the live …/pose stream itself (map frame), on the overlap, against session 1
        idx = sorted(i for i in live_T if 40 + i < 100)
        if idx:
            d = np.linalg.norm(np.array([live_T[i][:3, 3] for i in idx]) - read_kitti_poses(s1_est)[[40 + i for i in idx], :3, 3], axis=1)
            path = float(np.sum(np.linalg.norm(np.diff(gt[[40 + i for i in idx], :3, 3], axis=0), axis=1)))
            out.update({"live_pose_overlap_frames": f"{40 + idx[0]}-{40 + idx[-1]}",
                        "live_pose_vs_session1_rmse_pct_of_path": 100 * float(np.sqrt(np.mean(d ** 2))) / path,
                        "live_pose_vs_session1_max_pct_of_path": 100 * float(d.max()) / path})
    return out
