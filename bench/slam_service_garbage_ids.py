"""500 garbage camera ids at a SLAM service: threads and memory before, at the peak, after eviction.

Every new ``metricslam/<id>/frame`` key is a camera to the service. This sends one malformed
frame on each of ``--ids`` new ids (what a scanner or a buggy client does) to a real service
process (``metricslam slam-service --depth-url none``, idle close after ``--idle-timeout-s``) and
samples its OS threads and RSS (``/proc/<pid>/status``): before, at the peak, and once the
service reports no open camera plus a settle time. Two configurations: the shipped camera cap
(8: ids beyond it get no thread at all) and a cap above ``--ids`` (every id gets a worker
thread until it is evicted).

    .venv/bin/python -m bench.slam_service_garbage_ids --out bench/results/slam_service_garbage_ids
"""

from __future__ import annotations

import argparse
import sys
import time

from bench.machine import command_line, describe, write_results
from bench.slam_service_soak import slam_service_child
from metricslam.wire import keys
from metricslam_slam.tools.client import query_health
from metricslam_slam.tools.soak import proc_status_value, rss_mib


def os_threads(pid: int) -> int:
    """Threads of process ``pid`` (Linux ``/proc/<pid>/status``)."""
    return proc_status_value(pid, "Threads")


def run_config(n_ids: int, max_cameras: int, idle_timeout_s: float, settle_s: float) -> dict:
    env = {"SLAM_MAX_CAMERAS": str(max_cameras), "SLAM_CAMERA_IDLE_TIMEOUT_S": str(idle_timeout_s)}
    with slam_service_child(env) as (client, proc):
        time.sleep(settle_s)
        before = {"threads": os_threads(proc.pid), "rss_mib": round(rss_mib(proc.pid), 1)}
        t0 = time.monotonic()
        for i in range(n_ids):
            client.put(keys.key(f"garbage-{i}", "frame"), b"\x00 not a frame " + i.to_bytes(4, "little"))
        peak = dict(before)
        while time.monotonic() - t0 < idle_timeout_s + 60:
            peak["threads"] = max(peak["threads"], os_threads(proc.pid))
            peak["rss_mib"] = max(peak["rss_mib"], round(rss_mib(proc.pid), 1))
            health = query_health(client, 1.0)
            if health is not None and health.get("malformed_frames", 0) + health.get("refused_frames", 0) >= n_ids \
                    and not health.get("cameras"):
                break
            time.sleep(0.2)
        evicted_s = time.monotonic() - t0
        time.sleep(settle_s)
        after = {"threads": os_threads(proc.pid), "rss_mib": round(rss_mib(proc.pid), 1)}
        health = query_health(client, 1.0) or {}
    return {"ids": n_ids, "max_cameras": max_cameras, "idle_timeout_s": idle_timeout_s, "before": before,
            "peak": peak, "after": after, "all_closed_after_s": round(evicted_s, 1),
            "malformed_frames": health.get("malformed_frames"), "refused_frames": health.get("refused_frames"),
            "cameras_closed": health.get("cameras_closed")}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ids", type=int, default=500)
    parser.add_argument("--idle-timeout-s", type=float, default=2.0, help="SLAM_CAMERA_IDLE_TIMEOUT_S for the run")
    parser.add_argument("--settle-s", type=float, default=3.0)
    parser.add_argument("--out", default="bench/results/slam_service_garbage_ids")
    args = parser.parse_args(argv)
    machine_before = describe()
    results = {f"cap {cap}": run_config(args.ids, cap, args.idle_timeout_s, args.settle_s)
               for cap in (8, args.ids + 10)}
    payload = {"command": command_line("bench.slam_service_garbage_ids", argv), "machine_before": machine_before,
               "machine_after": describe(), "results": results}
    rows = ["| camera cap | OS threads before / peak / after | RSS MiB before / peak / after | all closed after s "
            "| malformed / refused frames | cameras closed |", "| --- | --- | --- | --- | --- | --- |"]
    for r in results.values():
        rows.append(f"| {r['max_cameras']} | {r['before']['threads']} / {r['peak']['threads']} / {r['after']['threads']} | "
                    f"{r['before']['rss_mib']} / {r['peak']['rss_mib']} / {r['after']['rss_mib']} | "
                    f"{r['all_closed_after_s']} | {r['malformed_frames']} / {r['refused_frames']} | {r['cameras_closed']} |")
    markdown = "\n".join([
        "# SLAM service: garbage camera ids", "", f"`{payload['command']}`", "",
        f"Machine before: {machine_before}", "", f"Machine after: {payload['machine_after']}", "",
        f"{args.ids} new camera ids, one malformed frame each, idle close after {args.idle_timeout_s:g} s; "
        f"'after' = once no camera is open, plus {args.settle_s:g} s.", "", *rows, ""])
    write_results(args.out, payload, markdown)
    print(markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
