"""Is the live stack metric from its first pose? The README recipe, measured (issue #19 item 1).

Runs the stack recipe as a user would — ``metricslam up``, ``metricslam poses --out EST.txt``
(default: unscaled poses skipped), ``metricslam replay SEQ --rate 10`` — on a KITTI sequence,
with the initial metric scale on (the service's default) and off
(``METRICSLAM_INITIAL_SCALE__ENABLED=false``: the behaviour before it), and records every live
pose with its scale state beside the CLI. For reference, offline: ``metricslam run`` (threaded
default and ``--deterministic``; the final, re-optimized trajectory) and the same deterministic
system in-process, scoring the poses *as processed* (what a live stream publishes, frame by
frame), with the initial scale on and off. Scale error is ``metricslam eval``'s (the Sim(3)
alignment's scale, ``scale_error_pct``).

Example::

    D=../shared/data/kitti_odometry
    nice -n 5 .venv/bin/python -m bench.stack_first_pose --seq $D/sequences/06 --gt $D/poses/06.txt \
        --repeats 2 --out bench/results/stack_first_pose
"""

from __future__ import annotations

import argparse
import os
import queue
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bench.accuracy import METRICSLAM as CLI
from bench.machine import command_line, describe, write_results


def _evaluate(gt: np.ndarray, est: np.ndarray, name: str) -> dict:
    from metricslam.evaluation.evaluator import evaluate_poses

    r = evaluate_poses(gt, est, name).result
    return {"scale_error_pct": r.scale_error_pct, "scale_ratio": r.scale_ratio,
            "ate_rmse_m": r.ate_rmse_m, "ate_rmse_sim3_m": r.ate_rmse_sim3_m, "n_frames": r.n_frames}


def _largest_jump_m(gt: np.ndarray, est: np.ndarray) -> float:
    """Largest frame-to-frame step error |Δp_est − Δp_gt| (m): a jump when scale arrives."""
    d_est = np.diff(est[:, :3, 3], axis=0)
    d_gt = np.diff(gt[:, :3, 3], axis=0)
    return float(np.max(np.linalg.norm(d_est - d_gt, axis=1)))


class _Up:
    """``metricslam up`` as a child; waits for its ``UP:`` line."""

    def __init__(self, endpoint: str, depth_port: int, log_dir: Path, env: dict) -> None:
        self.proc = subprocess.Popen(CLI + ["up", "--zenoh-endpoint", endpoint, "--depth-port", str(depth_port),
                                            "--log-dir", str(log_dir)],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=lambda: [self.lines.put(x) for x in self.proc.stdout], daemon=True).start()
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                if self.lines.get(timeout=1.0).startswith("UP:"):
                    return
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
        self.stop()
        raise RuntimeError(f"metricslam up did not come up; logs in {log_dir}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(2)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def live_run(seq_dir: Path, gt: np.ndarray, work: Path, initial_scale: bool, rate_hz: float) -> dict:
    """One pass of the recipe; returns what the CLI recorded and what was published."""
    from metricslam_slam.supervisor.launcher import free_port
    from metricslam_slam.tools.client import PoseRecorder, finish_camera, query_trajectory
    from metricslam_slam.zenoh_config import open_client

    from metricslam.trajectory.io import read_kitti_poses

    n = len(gt)
    env = dict(os.environ, PYTHONUNBUFFERED="1",
               METRICSLAM_INITIAL_SCALE__ENABLED="true" if initial_scale else "false")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    up = _Up(endpoint, free_port(), work / "logs", env)
    try:
        session = open_client(endpoint)
        watch = PoseRecorder(session, "cam0")
        est = work / "live.txt"
        poses = subprocess.Popen(CLI + ["poses", "--zenoh-endpoint", endpoint, "--out", str(est),
                                        "--frames", str(n), "--timeout", "180"],
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        assert poses.stdout.readline().startswith("recording")
        replay = subprocess.run(CLI + ["replay", str(seq_dir), "--zenoh-endpoint", endpoint,
                                       "--rate", str(rate_hz), "--no-progress", "--allow-loss"],
                                capture_output=True, text=True, env=env, timeout=300)
        poses_out = poses.communicate(timeout=240)[0]
        watch.wait_frames(n, 30)
        watch.close()
        finish_camera(session, "cam0", "bench.stack_first_pose")  # as `poses --trajectory --finish`
        trajectory = query_trajectory(session, "cam0")
        session.close()
    finally:
        up.stop()
    msgs = [watch.poses[i] for i in range(n) if i in watch.poses]
    states = [m.effective_scale_state().value for m in msgs]
    T_all = np.array([m.T_world_cam for m in msgs]) if len(msgs) == n else None
    out = {"initial_scale": initial_scale, "replay_rc": replay.returncode,
           "replay": (replay.stdout + replay.stderr).strip().splitlines()[-1:],
           "poses_rc": poses.returncode, "poses_output": poses_out.strip().splitlines(),
           "published": len(msgs), "states": {s: states.count(s) for s in ("unscaled", "provisional", "metric")},
           "first_provisional_frame": states.index("provisional") if "provisional" in states else None,
           "first_metric_frame": states.index("metric") if "metric" in states else None}
    if poses.returncode == 0:
        out["recorded"] = _evaluate(gt, read_kitti_poses(est), "recorded (poses default)")
    held = trajectory.frame_index
    if len(held) >= 3 and held.max() < n:
        out["optimized"] = _evaluate(gt[held], trajectory.T_world_cam, "optimized …/trajectory")
        out["optimized"]["frames"] = int(len(held))
    if T_all is not None:
        out["published_all"] = _evaluate(gt, T_all, "every published pose")
        out["largest_jump_m"] = _largest_jump_m(gt, T_all)
        keep = np.array([s != "unscaled" for s in states])
        if keep.sum() >= 3:
            out["published_scaled"] = _evaluate(gt[keep], T_all[keep], "published, scaled only")
    return out


def offline_run(seq_dir: Path, gt: np.ndarray, work: Path, deterministic: bool) -> dict:
    import json

    from metricslam.trajectory.io import read_kitti_poses

    est, stats = work / "offline.txt", work / "offline.json"
    subprocess.run(CLI + ["run", str(seq_dir), "--out", str(est), "--json", str(stats), "--no-progress"]
                   + (["--deterministic"] if deterministic else []), check=True, capture_output=True, text=True)
    info = json.loads(stats.read_text())
    return {"deterministic": deterministic, **_evaluate(gt, read_kitti_poses(est), "offline"),
            "scale_states": info.get("scale_states")}


def offline_as_processed(seq_dir: Path, gt: np.ndarray, initial_scale: bool) -> dict:
    """The deterministic system in-process; scores the pose ``process`` returned for each frame."""
    from metricslam.datasets import open_sequence
    from metricslam.datasets.frame_reader import FrameReader
    from metricslam.slam.config_file import load_system_config
    from metricslam.slam.session_builder import build_session, preset_for

    seq = open_sequence(seq_dir)
    config = load_system_config(None, env={}, overrides={
        "deterministic": True, "initial_scale": {"enabled": initial_scale}})
    pipe = build_session(seq.camera, config, default_preset=preset_for(seq_dir))
    frames = FrameReader(seq)
    try:
        live = [pipe.process(frames[i]) for i in range(len(seq))]
    finally:
        pipe.close()
    T = np.array([e.T_world_cam for e in live])
    stats = pipe.stats()
    return {"initial_scale": initial_scale, **_evaluate(gt, T, "offline as processed"),
            "largest_jump_m": _largest_jump_m(gt, T), "scale_states": stats["scale_states"],
            "initial": stats["initial_scale"]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", type=Path, required=True, help="KITTI sequence folder")
    p.add_argument("--gt", type=Path, required=True, help="its KITTI ground-truth pose file")
    p.add_argument("--rate", type=float, default=10.0, help="replay rate (Hz), as in the README")
    p.add_argument("--repeats", type=int, default=1, help="live runs per setting (threaded: they differ)")
    p.add_argument("--initial-scale", choices=("both", "on"), default="both",
                   help="'on': only the service's default (skip the runs with the initial scale off)")
    p.add_argument("--out", required=True, metavar="PREFIX")
    args = p.parse_args(argv)
    from metricslam.trajectory.io import read_kitti_poses

    gt = read_kitti_poses(args.gt)
    machine = describe()
    live, offline, processed = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeats):
            for initial in (True, False) if args.initial_scale == "both" else (True,):
                work = Path(tmp) / f"live_{int(initial)}_{k}"
                (work / "logs").mkdir(parents=True)
                live.append(live_run(args.seq, gt, work, initial, args.rate))
                print(live[-1], flush=True)
        for deterministic in (False, True):
            work = Path(tmp) / f"offline_{int(deterministic)}"
            work.mkdir()
            offline.append(offline_run(args.seq, gt, work, deterministic))
            print(offline[-1], flush=True)
        for initial in (True, False) if args.initial_scale == "both" else (True,):
            processed.append(offline_as_processed(args.seq, gt, initial))
            print(processed[-1], flush=True)
    payload = {"command": command_line("bench.stack_first_pose", argv), "machine": machine,
               "sequence": str(args.seq), "rate_hz": args.rate, "live": live, "offline": offline,
               "offline_as_processed": processed}
    write_results(args.out, payload, _markdown(payload))
    print(_markdown(payload))
    return 0


def _markdown(payload: dict) -> str:
    def f(x, fmt="{:.1f}"):
        return "n/a" if x is None else fmt.format(x)

    rows = ["| run | unscaled / provisional / metric published | recorded by `poses` (scale err) | "
            "every published pose (scale err) | largest jump | optimized `…/trajectory` at the end (scale err) |",
            "| --- | --- | --- | --- | --- | --- |"]
    for r in payload["live"]:
        st = r["states"]
        rows.append(f"| live, initial scale {'on' if r['initial_scale'] else 'off (before)'} | "
                    f"{st['unscaled']} / {st['provisional']} / {st['metric']} | "
                    f"{f(r.get('recorded', {}).get('scale_error_pct'))} % | "
                    f"{f(r.get('published_all', {}).get('scale_error_pct'))} % | "
                    f"{f(r.get('largest_jump_m'), '{:.2f}')} m | "
                    f"{f(r.get('optimized', {}).get('scale_error_pct'))} % |")
    for r in payload["offline_as_processed"]:
        st = r["scale_states"]
        rows.append(f"| offline `--deterministic`, poses as processed, initial scale "
                    f"{'on' if r['initial_scale'] else 'off'} | {st['unscaled']} / {st['provisional']} / "
                    f"{st['metric']} | | {f(r['scale_error_pct'])} % | {f(r['largest_jump_m'], '{:.2f}')} m | |")
    for r in payload["offline"]:
        rows.append(f"| offline `run`{' --deterministic' if r['deterministic'] else ''}, final "
                    f"trajectory | | {f(r['scale_error_pct'])} % | | | |")
    return (f"# The live stack from its first pose ({Path(payload['sequence']).name}, "
            f"{payload['rate_hz']:g} Hz)\n\n" + "\n".join(rows) + "\n\n"
            f"Command: `{payload['command']}`\n\nMachine: {payload['machine']}\n")


if __name__ == "__main__":
    sys.exit(main())
