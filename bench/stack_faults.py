"""Faults in the live stack, measured (issue #19): kill -9 and SIGSTOP of each child of
``metricslam up`` during a replay. Is every lost frame reported, does the supervisor recover,
and is the trajectory continuous across a restart of the SLAM service?

For each child (zenoh router, depth service, SLAM service) and each fault (``kill``: SIGKILL;
``stop``: SIGSTOP for ``--stop-s`` seconds, then SIGCONT), and once without a fault: a fresh
stack (``metricslam up`` with its defaults, explicit free ports, a fresh ``SLAM_STATE_DIR``),
``metricslam poses --all`` recording, and ``metricslam replay SEQ --rate 10`` (the README recipe)
of ``--seconds`` of the sequence played forwards and backwards
(:func:`bench.stack_process.ping_pong_sequence`; 51 frames last 5 s). The fault goes to the
child's pid (``up`` prints it) ``--fault-at`` seconds after the first pose. Recorded per run:

* frames sent / confirmed / reported lost (``replay``'s own line) and its exit code (non-zero
  when frames were lost); frames with no pose at all (neither seen by an independent watcher nor
  in the service's ``…/trajectory`` afterwards); **silent loss** = frames without a pose beyond
  what ``replay`` reported, or a loss with exit code 0;
* what ``poses`` wrote (it fails when a frame has no pose);
* the supervisor's restarts and hung-kills after the fault, the time to its restart, to the
  first pose after the longest pose gap following the fault, and (depth faults) until
  ``…/status`` says the depth service is reachable again;
* the trajectory: frames before and after the restart, ``session_restarted`` on the status key,
  the step across the seam and the largest step near it over the median step, and how far the
  camera really moved (ground truth) between the two poses that meet at the seam.

Example::

    .venv/bin/python -m bench.stack_faults --seq ../shared/data/kitti_odometry/sequences/06 \
        --out bench/results/stack_faults
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.machine import command_line, describe, write_results
from bench.stack_process import CLI, UpProcess, Watcher, pick_port, ping_pong_sequence, running

CHILDREN = ("zenoh-router", "depth-service", "slam-service")
FAULTS = ("kill", "stop")
CAMERA = "cam0"
UP_DEFAULTS = "restart delay 1 s doubling to 30 s, hang timeout 20 s, probe period 2 s"
ENV_PREFIXES = ("SLAM_", "METRICSLAM_", "DEPTH_", "ZENOH_")  # settings the stack reads: recorded


def inject(up: UpProcess, child: str, fault: str, stop_s: float) -> dict:
    """Send the fault to ``child``'s current pid; for ``stop``, SIGCONT after ``stop_s`` unless
    the supervisor killed it meanwhile. Returns when it was sent and to which pid."""
    pid = up.pid(child)
    t_fault = time.perf_counter()
    if fault == "kill":
        os.kill(pid, signal.SIGKILL)
        return {"pid": pid, "t_fault": t_fault}
    os.kill(pid, signal.SIGSTOP)
    time.sleep(stop_s)
    resumed = running(pid)
    if resumed:
        os.kill(pid, signal.SIGCONT)
    return {"pid": pid, "t_fault": t_fault, "stopped_s": round(time.perf_counter() - t_fault, 2),
            "resumed": resumed}


def parse_replay(text: str) -> dict:
    """``sent N frames …; the SLAM service confirmed M …; K without a pose`` -> numbers."""
    def num(pattern: str) -> int | None:
        m = re.search(pattern, text)
        return int(m.group(1)) if m else None

    return {"sent": num(r"sent (\d+) frames"), "confirmed": num(r"confirmed (\d+)"),
            "reported_lost": num(r"; (\d+) without a pose") or 0}


def recovery(watcher: Watcher, up: UpProcess, child: str, t_fault: float) -> dict:
    """Restarts after the fault and how long until things flowed again (s from the fault)."""
    events = up.events_after(t_fault)
    restarted = [t for t, name, what, _ in events if name == child and what == "restarted"]
    out = {"restarts": {n: sum(1 for _, name, what, _ in events if name == n and what == "restarted")
                        for n in CHILDREN},
           "hung_kills": [name for _, name, what, _ in events if what == "hung"],
           "restart_s": round(restarted[0] - t_fault, 2) if restarted else None}
    t = watcher.arrivals_s()
    t = t[t >= t_fault - 0.5]
    if len(t) >= 2:
        gaps = np.diff(t)
        k = int(np.argmax(gaps))
        out["longest_pose_gap_s"] = round(float(gaps[k]), 2)
        out["poses_resume_s"] = round(float(t[k + 1] - t_fault), 2) if gaps[k] > 1.0 else 0.0
    statuses = [(ts, s) for ts, s in watcher.statuses if ts >= t_fault]
    down = [ts for ts, s in statuses if s.depth_reachable is False]
    if child == "depth-service":
        back = [ts for ts, s in statuses if s.depth_reachable is True and down and ts > down[0]]
        out["depth_unreachable_seen"] = bool(down)
        out["depth_back_s"] = round(back[0] - t_fault, 2) if back else None
    return out


def continuity(watcher: Watcher, trajectory, gt: np.ndarray | None) -> dict:
    """The optimized trajectory after the run: coverage, its largest step (with the real motion
    over the same frames: a lost frame makes a step span several frames), and the seam where a
    restarted SLAM service's new segment starts."""
    if trajectory is None or len(trajectory.frame_index) < 2:
        return {"trajectory_frames": 0 if trajectory is None else len(trajectory.frame_index)}
    idx = np.asarray(trajectory.frame_index)
    p = np.asarray(trajectory.T_world_cam)[:, :3, 3]
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    real = (np.linalg.norm(np.diff(gt[idx, :3, 3], axis=0), axis=1)
            if gt is not None and idx.max() < len(gt) else None)
    consecutive = np.diff(idx) == 1
    median_step = float(np.median(steps[consecutive])) if consecutive.any() else float("nan")

    def step(k: int) -> dict:  # the step from idx[k] to idx[k + 1]
        return {"to_frame": int(idx[k + 1]), "frames_spanned": int(idx[k + 1] - idx[k]),
                "step_m": round(float(steps[k]), 2), "over_median": round(float(steps[k] / median_step), 2),
                "real_m": None if real is None else round(float(real[k]), 2)}

    out = {"trajectory_frames": int(len(idx)), "median_step_m": round(median_step, 3),
           "largest_step": step(int(np.argmax(steps)))}
    live = sorted(watcher.recorder.poses.items())
    if len(live) >= 2:  # what subscribers saw: a restart without state jumps back to the origin
        live_p = np.array([m.T_world_cam[:3, 3] for _, m in live])
        live_steps = np.linalg.norm(np.diff(live_p, axis=0), axis=1)
        j = int(np.argmax(live_steps))
        out["largest_live_step"] = {"to_frame": live[j + 1][0], "frames_spanned": live[j + 1][0] - live[j][0],
                                    "step_m": round(float(live_steps[j]), 2),
                                    "real_m": None if gt is None or live[j + 1][0] >= len(gt) else round(float(
                                        np.linalg.norm(gt[live[j + 1][0], :3, 3] - gt[live[j][0], :3, 3])), 2)}
    restarts = [detail for _, event, detail in watcher.events() if event == "session_restarted"]
    out["session_restarted"] = restarts
    m = re.search(r"as segment (\d+)", restarts[0]) if restarts else None
    after = sorted(i for i, msg in watcher.recorder.poses.items() if m and msg.segment_id >= int(m.group(1)))
    k = int(np.searchsorted(idx, after[0])) if after else 0
    if 0 < k < len(idx) and idx[k] == after[0]:
        near = steps[max(k - 10, 0):k + 10]
        out["seam"] = {**step(k - 1), "frames_before": k, "frames_after": int(len(idx) - k),
                       "max_near_over_median": round(float(near.max() / median_step), 2)}
    return out


def run_case(child: str | None, fault: str | None, seq_dir: Path, n_frames: int, gt: np.ndarray | None,
             work: Path, args: argparse.Namespace, ports: set[int]) -> dict:
    """One fresh stack, one replay, at most one fault; returns the run's record."""
    from metricslam_slam.tools.client import query_trajectory
    from metricslam_slam.zenoh_config import open_client

    endpoint = f"tcp/127.0.0.1:{pick_port(args.router_port, ports)}"
    depth_port = pick_port(args.depth_port, ports)
    env = dict(os.environ, PYTHONUNBUFFERED="1", SLAM_STATE_DIR=str(work / "state"))
    if args.no_state_dir:  # `up` as the recipe runs it: whatever state it gives its SLAM service
        del env["SLAM_STATE_DIR"]
    up = UpProcess(["--zenoh-endpoint", endpoint, "--depth-port", str(depth_port),
                    "--log-dir", str(work / "logs"), *shlex.split(args.up_args)], env)
    record: dict = {"child": child, "fault": fault, "endpoint": endpoint, "depth_port": depth_port}
    session = watcher = poses = replay = None
    try:
        up.wait_up()
        session = open_client(endpoint)
        watcher = Watcher(session, CAMERA)
        poses = subprocess.Popen(CLI + ["poses", "--zenoh-endpoint", endpoint, "--out", str(work / "poses.txt"),
                                        "--frames", str(n_frames), "--all",
                                        "--timeout", str(args.seconds + 40)],
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        assert poses.stdout.readline().startswith("recording")
        t_replay = time.perf_counter()
        replay = subprocess.Popen(CLI + ["replay", str(seq_dir), "--zenoh-endpoint", endpoint,
                                         "--rate", str(args.rate), "--no-progress"],
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        if not watcher.recorder.wait_frames(1, 90):
            raise RuntimeError("no pose within 90 s of the replay's start")
        t_first = time.perf_counter()
        record["first_pose_s"] = round(t_first - t_replay, 2)
        if child is not None:
            time.sleep(max(t_first + args.fault_at - time.perf_counter(), 0.0))
            at_frame = max(watcher.recorder.received_frames(), default=None)
            record["fault"] = {"kind": fault, "at_frame": at_frame, **inject(up, child, fault, args.stop_s)}
        replay_out = replay.communicate(timeout=args.seconds + 300)[0]
        record["replay_rc"] = replay.returncode
        record["replay_line"] = replay_out.strip().splitlines()[-1:] if replay_out.strip() else []
        record.update(parse_replay(replay_out))
        poses_out = poses.communicate(timeout=args.seconds + 120)[0]
        record["poses_rc"] = poses.returncode
        record["poses_line"] = poses_out.strip().splitlines()[-1:]
        time.sleep(2.0)  # the last statuses
        try:
            trajectory = query_trajectory(session, CAMERA, timeout_s=10.0)
        except Exception as exc:  # noqa: BLE001 -- recorded, not fatal to the benchmark
            trajectory, record["trajectory_error"] = None, str(exc)
        record.update(_losses(record, watcher, trajectory))
        if child is not None:
            record["recovery"] = recovery(watcher, up, child, record["fault"]["t_fault"])
        record["continuity"] = continuity(watcher, trajectory, gt)
        _keep(work, watcher, trajectory)
        last = watcher.recorder.latest_status()
        record["last_status"] = None if last is None else {
            k: getattr(last, k) for k in ("frames_received", "frames_processed", "queue_drops", "malformed",
                                          "depth_reachable", "depth_outages", "scale_established")}
        record["status_events"] = [(e, d) for _, e, d in watcher.events()]
    finally:
        for proc in (replay, poses):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
        if watcher is not None:
            watcher.close()
        if session is not None:
            session.close()
        record["up_rc"] = up.stop()
        record["supervisor_lines"] = [x for x in up.lines if re.match(r"^[\w-]+\s+(restarted|hung)", x)]
    return record


def _keep(work: Path, watcher: Watcher, trajectory) -> None:
    """The run's poses beside its logs: the final trajectory and every live pose's segment."""
    live = sorted(watcher.recorder.poses.items())
    np.savez_compressed(work / "poses.npz",
                        live_frame=np.array([i for i, _ in live], dtype=np.int64),
                        live_segment=np.array([m.segment_id for _, m in live], dtype=np.int64),
                        live_T=np.array([m.T_world_cam for _, m in live]).reshape(-1, 4, 4),
                        frame=np.asarray([] if trajectory is None else trajectory.frame_index, dtype=np.int64),
                        T=np.asarray([] if trajectory is None else trajectory.T_world_cam).reshape(-1, 4, 4))


def _losses(record: dict, watcher: Watcher, trajectory) -> dict:
    sent = record.get("sent") or 0
    have = watcher.recorder.received_frames()
    if trajectory is not None:
        have |= {int(i) for i in trajectory.frame_index}
    no_pose = [i for i in range(sent) if i not in have]
    reported = record.get("reported_lost", 0)
    confirmed = record.get("confirmed")
    consistent = confirmed is not None and sent - confirmed == reported
    silent = len(no_pose) > reported or (bool(no_pose) and record["replay_rc"] == 0) or not consistent
    return {"watcher_poses": len(watcher.recorder.poses), "no_pose_frames": len(no_pose),
            "no_pose_first": no_pose[:10], "counts_consistent": consistent, "silent_loss": silent,
            "over_reported": max(reported - len(no_pose), 0)}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", type=Path, required=True, help="KITTI-layout sequence folder (played back and forth)")
    p.add_argument("--out", required=True, metavar="PREFIX")
    p.add_argument("--rate", type=float, default=10.0, help="replay rate (Hz), as in the README recipe")
    p.add_argument("--seconds", type=float, default=45.0, help="replay length (s at --rate)")
    p.add_argument("--fault-at", type=float, default=12.5,
                   help="s after the first pose (12.5: mid-lap, away from where the ping-pong turns)")
    p.add_argument("--stop-s", type=float, default=15.0, help="SIGSTOP duration (s)")
    p.add_argument("--cases", nargs="*", default=None, metavar="CHILD:FAULT",
                   help="e.g. slam-service:kill none (default: none and every child × fault)")
    p.add_argument("--router-port", type=int, default=27447, help="first router port tried")
    p.add_argument("--depth-port", type=int, default=28100, help="first depth port tried")
    p.add_argument("--keep", type=Path, help="keep each run's logs, state and poses here")
    p.add_argument("--no-state-dir", action="store_true",
                   help="no SLAM_STATE_DIR for `up` (the README recipe as it is), instead of a fresh one per run")
    p.add_argument("--up-args", default="", metavar="'ARGS'",
                   help="extra `metricslam up` arguments, e.g. '--hang-timeout 10' (default: none)")
    args = p.parse_args(argv)
    cases = args.cases or ["none"] + [f"{c}:{f}" for c in CHILDREN for f in FAULTS]
    machine_start = describe()
    n_frames = int(round(args.seconds * args.rate))
    ports: set[int] = set()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        seq_dir = root / f"pingpong_{n_frames}"
        if not seq_dir.exists():
            ping_pong_sequence(args.seq, seq_dir, n_frames)
        from metricslam.datasets import open_sequence

        gt = open_sequence(seq_dir).T_world_cam_gt
        for k, case in enumerate(cases):
            child, _, fault = case.partition(":")
            child, fault = (None, None) if child == "none" else (child, fault)
            if child is not None and (child not in CHILDREN or fault not in FAULTS):
                p.error(f"unknown case {case!r}: CHILD:FAULT with CHILD in {CHILDREN}, FAULT in {FAULTS}")
            work = root / f"{k:02d}_{case.replace(':', '_')}"
            work.mkdir(parents=True)
            runs.append(run_case(child, fault, seq_dir, n_frames, gt, work, args, ports))
            print({k: v for k, v in runs[-1].items() if k not in ("status_events", "supervisor_lines")}, flush=True)
    payload = {"command": command_line("bench.stack_faults", argv), "machine": machine_start,
               "machine_at_end": describe(), "sequence": str(args.seq), "rate_hz": args.rate,
               "replay_frames": n_frames, "fault_at_s": args.fault_at, "stop_s": args.stop_s,
               "up_args": args.up_args, "up_defaults": UP_DEFAULTS, "fresh_state_dir": not args.no_state_dir,
               "environment": {k: v for k, v in sorted(os.environ.items()) if k.startswith(ENV_PREFIXES)},
               "runs": runs}
    text = markdown(payload)
    write_results(args.out, payload, text)
    print(text)
    return 0


def _name(r: dict) -> str:
    return "no fault" if r["child"] is None else f"{r['child']} {r['fault']['kind']}"


def _env(payload: dict) -> str:
    env = payload.get("environment") or {}
    return (" with " + ", ".join(f"`{k}={v}`" for k, v in env.items())) if env else ""


def markdown(payload: dict) -> str:
    def f(x, fmt="{}"):
        return "n/a" if x is None else fmt.format(x)

    rows = ["| case | replay exit | sent | confirmed | reported lost | no pose at all | silent loss | "
            "poses seen / `poses` exit | restarts after the fault | restart (s) | poses resume (s) | "
            "depth reachable again (s) |", "| --- " * 12 + "|"]
    steps = ["| case | trajectory frames | largest step: m (frames spanned) | real motion there (m) | "
             "step / median | largest live step: m (frames spanned) / real (m) | `session_restarted` | "
             "frames before / after the seam | seam step (m) | real motion across the seam (m) | "
             "largest step within 10 of the seam / median |", "| --- " * 11 + "|"]
    for r in payload["runs"]:
        rec = r.get("recovery", {})
        restarts = ", ".join(f"{n} {k}" for n, k in rec.get("restarts", {}).items() if k) or ("0" if rec else "")
        if rec.get("hung_kills"):
            restarts += f" (hung: {', '.join(rec['hung_kills'])})"
        rows.append(f"| {_name(r)} | {f(r.get('replay_rc'))} | {f(r.get('sent'))} | {f(r.get('confirmed'))} | "
                    f"{r.get('reported_lost', 0)} | {f(r.get('no_pose_frames'))} | "
                    f"{'**yes**' if r.get('silent_loss') else 'no'} | {f(r.get('watcher_poses'))} / "
                    f"{f(r.get('poses_rc'))} | {restarts} | {f(rec.get('restart_s'))} | "
                    f"{f(rec.get('poses_resume_s'))} | {f(rec.get('depth_back_s'))} |")
        c = r.get("continuity", {})
        big, seam, live = c.get("largest_step", {}), c.get("seam", {}), c.get("largest_live_step", {})
        slam_restarts = rec.get("restarts", {}).get("slam-service", 0)
        restarted = "yes" if c.get("session_restarted") else ("**no**" if slam_restarts else "no")
        steps.append(f"| {_name(r)} | {c.get('trajectory_frames')} | {f(big.get('step_m'))} "
                     f"({f(big.get('frames_spanned'))}) | {f(big.get('real_m'))} | {f(big.get('over_median'))} | "
                     f"{f(live.get('step_m'))} ({f(live.get('frames_spanned'))}) / {f(live.get('real_m'))} | {restarted} | {f(seam.get('frames_before'))} / {f(seam.get('frames_after'))} | "
                     f"{f(seam.get('step_m'))} | {f(seam.get('real_m'))} | {f(seam.get('max_near_over_median'))} |")
    return (f"# Faults in the live stack ({Path(payload['sequence']).name} played back and forth, "
            f"{payload['replay_frames']} frames at {payload['rate_hz']:g} Hz)\n\n"
            f"Each run: a fresh `{('metricslam up ' + payload['up_args']).strip()}` (defaults otherwise: "
            f"{payload['up_defaults']}){_env(payload)}, "
            + ("a fresh `SLAM_STATE_DIR`, " if payload.get("fresh_state_dir", True) else "no `SLAM_STATE_DIR`, ") +
            f"`poses --all`, `replay --rate {payload['rate_hz']:g}`; the fault {payload['fault_at_s']:g} s after "
            f"the first pose (`kill`: SIGKILL; `stop`: SIGSTOP for {payload['stop_s']:g} s, then SIGCONT). "
            "Times are from the fault. *No pose at all*: sent frames neither an independent subscriber "
            "saw a pose of nor the service's `…/trajectory` holds after the run; *silent loss*: more of "
            "them than `replay` reported, or a loss with exit code 0.\n\n" + "\n".join(rows) + "\n\n"
            "The optimized `…/trajectory` after the run (steps between consecutive poses it holds; real "
            "motion from the ground truth over the same frames; the seam is where the restarted SLAM "
            "service's new segment starts):\n\n" + "\n".join(steps) + "\n\n"
            f"Command: `{payload['command']}`\n\nMachine: {payload['machine']}\n\n"
            f"At the end: {payload['machine_at_end']}\n")


if __name__ == "__main__":
    sys.exit(main())
