"""Frame-in -> pose-out latency of the SLAM service over Zenoh, the highest frame rate it
sustains without drops, and two cameras at once.

Runs the real stack as child processes (zenoh router, depth service, SLAM service: exactly what
``metricslam up`` starts) on loopback, publishes a sequence's frames from this process at fixed
rates (no back-pressure) and times each frame from ``put`` to the arrival of its pose. Each trial
uses a fresh camera id, so a fresh SLAM session. A second stack with ``--session identity``
(every frame answered with the identity pose) separates transport cost from SLAM cost.

    .venv/bin/python -m bench.zenoh_latency --seq ../shared/data/kitti_odometry/sequences/06
    # writes bench/results/zenoh.md (and .json)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import threading
import time
from pathlib import Path

import numpy as np

from bench.machine import command_line
from metricslam.datasets import open_sequence
from metricslam_slam.supervisor.launcher import Stack, free_port
from metricslam_slam.tools.client import FramePublisher, PoseRecorder
from metricslam_slam.tools.replay import wait_for_service
from metricslam_slam.zenoh_config import open_client


def trial(session, frames, camera_id: str, rate_hz: float, drain_s: float = 15.0) -> dict:
    """Publish ``frames`` (list of Frame) at ``rate_hz``; latency stats and drops."""
    recorder = PoseRecorder(session, camera_id)
    publisher = FramePublisher(session, camera_id, block=True)
    if not publisher.wait_for_subscriber(10):
        raise SystemExit(f"no SLAM service subscribed to {camera_id}'s frames within 10 s")
    sent_ns: dict[int, int] = {}
    t0 = time.monotonic()
    for k, frame in enumerate(frames):
        delay = t0 + k / rate_hz - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        sent_ns[k] = publisher.publish(k, frame.t_ns, frame.image, frame.camera)
    send_s = time.monotonic() - t0
    recorder.wait_frames(len(frames), drain_s)
    recorder.wait_for(lambda r: (s := r.latest_status()) is not None
                      and s.frames_received >= len(frames) and s.queue_depth == 0, 5)
    status = recorder.latest_status()
    ks = sorted(k for k in recorder.poses if k in sent_ns)
    lat = np.array([(recorder.arrival_ns[k] - sent_ns[k]) / 1e6 for k in ks])
    worst = np.argsort(-lat)[:20] if lat.size else []
    publisher.close()
    recorder.close()
    return {"camera_id": camera_id, "rate_hz": rate_hz, "frames": len(frames),
        "achieved_send_hz": len(frames) / send_s if send_s > 0 else None,
        "poses": len(lat), "queue_drops": status.queue_drops if status else None,
        "p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
        "p99_ms": float(np.percentile(lat, 99)) if lat.size else None,
        "max_ms": float(lat.max()) if lat.size else None, "service_fps": status.fps if status else None,
        # where the tail is: the 20 slowest frames (index, ms) and p99 per 100 frames
        "slowest_frames": [[int(ks[i]), round(float(lat[i]), 1)] for i in worst],
        "p99_ms_per_100_frames": [round(float(np.percentile(lat[j:j + 100], 99)), 1) for j in range(0, lat.size, 100)],
    }


def run_stack(kind: str, frames, rates: list[float], two_cams: bool, log_dir: Path) -> dict:
    log_dir.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stack = Stack(endpoint, depth_port=free_port(), use_scale=(kind == "pipeline"), session_kind=kind,
                  log_dir=str(log_dir))
    out: dict = {"kind": kind, "sweep": [], "two_cameras": None}
    stack.start()
    session = open_client(endpoint)
    try:
        wait_for_service(session, 30, endpoint)
        trial(session, frames[:10], f"{kind}-warmup", 10.0)  # imports, first session
        for rate in rates:
            res = trial(session, frames, f"{kind}-r{rate:g}", rate)
            print(json.dumps(res), flush=True)
            out["sweep"].append(res)
            if res["queue_drops"] or res["poses"] < res["frames"]:
                break  # the next, higher rate would drop as well
        if two_cams:
            results: list[dict] = []
            threads = [threading.Thread(target=lambda cid=cid: results.append(trial(session, frames, cid, 10.0)))
                       for cid in (f"{kind}-camA", f"{kind}-camB")]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            print(json.dumps(results), flush=True)
            out["two_cameras"] = results
    finally:
        session.close()
        stack.stop()
    return out


def _fmt(x, f="{:.1f}"):
    return "n/a" if x is None else f.format(x)


def write_markdown(path: Path, results: list[dict], args: argparse.Namespace, n_frames: int, shape) -> None:
    lines = ["# SLAM service over Zenoh: latency, sustained rate, two cameras", "",
        f"Command: `{command_line('bench.zenoh_latency')}`  ",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. "
        f"Load average {os.getloadavg()[0]:.1f} at the end (the machine may be shared: compare "
        "runs only at similar loads).  ",
        f"Input: `{args.seq}`, {n_frames} frames of {shape[1]}x{shape[0]} gray, published from one "
        "process through a zenoh router process to the SLAM service process (all loopback TCP).",
        "Latency = `put` of the frame -> arrival of its pose at the publisher process (same clock).",
        "A rate 'sustained' = every frame got a pose and the service's drop-oldest queue "
        "(8 frames) dropped none. The sweep stops at the first rate that drops.", ""]
    for res in results:
        title = ("Real SLAM pipeline (VO + global graph + HTTP depth service)" if res["kind"] == "pipeline"
                 else "Transport only (`--session identity`: no SLAM work)")
        lines += [f"## {title}", "", "| rate Hz | sent Hz | poses | drops | p50 ms | p99 ms | max ms | service fps |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in res["sweep"]:
            lines.append(f"| {r['rate_hz']:g} | {_fmt(r['achieved_send_hz'])} | {r['poses']}/{r['frames']} | "
                         f"{r['queue_drops']} | {_fmt(r['p50_ms'])} | {_fmt(r['p99_ms'])} | "
                         f"{_fmt(r['max_ms'])} | {_fmt(r['service_fps'])} |")
        for r in res["sweep"]:
            if r.get("slowest_frames"):
                lines += ["", f"{r['rate_hz']:g} Hz, slowest frames (index: ms): "
                          + ", ".join(f"{k}: {ms:g}" for k, ms in r["slowest_frames"][:10])
                          + "; p99 per 100 frames: " + ", ".join(f"{x:g}" for x in r["p99_ms_per_100_frames"])]
        ok = [r["rate_hz"] for r in res["sweep"] if not r["queue_drops"] and r["poses"] == r["frames"]]
        lines += ["", f"Highest rate sustained without drops: **{max(ok):g} Hz**" if ok else
                  "No rate sustained without drops.", ""]
        if res["two_cameras"]:
            lines += ["Two cameras at once (10 Hz each, separate sessions in one service):", "",
                      "| camera | poses | drops | p50 ms | p99 ms |", "| --- | --- | --- | --- | --- |"]
            for r in res["two_cameras"]:
                lines.append(f"| {r['camera_id']} | {r['poses']}/{r['frames']} | {r['queue_drops']} | "
                             f"{_fmt(r['p50_ms'])} | {_fmt(r['p99_ms'])} |")
            lines.append("")
    path.write_text("\n".join(lines) + "\n")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seq", required=True, help="sequence folder (KITTI layout, e.g. KITTI 06 or synth output)")
    parser.add_argument("--frames", type=int, default=None, help="frames per trial (default: all)")
    parser.add_argument("--rates", default="10,15,20,30,40", help="pipeline rates to sweep (Hz)")
    parser.add_argument("--transport-rates", default="10,30,100,200,400", help="identity-session rates (Hz)")
    parser.add_argument("--out", default="bench/results/zenoh.md")
    parser.add_argument("--log-dir", default="/tmp/metricslam-bench-zenoh")
    parser.add_argument("--stacks", nargs="+", choices=("pipeline", "identity"), default=["pipeline", "identity"],
                        help="which stacks to run (identity: the transport-only reference)")
    parser.add_argument("--no-two-cameras", action="store_true", help="skip the two-cameras-at-once trial")
    args = parser.parse_args()
    seq = open_sequence(args.seq)
    n = len(seq) if args.frames is None else min(args.frames, len(seq))
    frames = [seq[i] for i in range(n)]  # decoded up front: time only the transport + SLAM
    Path(args.log_dir).mkdir(parents=True, exist_ok=True)
    rates = {"pipeline": args.rates, "identity": args.transport_rates}
    results = [run_stack(kind, frames, [float(r) for r in rates[kind].split(",")], not args.no_two_cameras,
                         Path(args.log_dir) / kind) for kind in args.stacks]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(results, indent=2))
    write_markdown(out, results, args, n, frames[0].image.shape)
    print(out.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
