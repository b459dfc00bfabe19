"""Memory of a long-running SLAM service: one camera fed a short rendered loop over and over.

The SLAM service runs as a child process (``metricslam slam-service --depth-url none``: learned
scale from the in-process depth model, so depth maps are part of what is held); this process is
the router and the camera. Its RSS is sampled every 50 frames (``/proc/<pid>/status``) while
``--frames`` frames of the ping-pong looped sequence go in with back-pressure
(:mod:`metricslam_slam.tools.soak`). Two configurations:

* ``defaults``: the shipped bounds (``SLAM_MAX_SESSION_KEYFRAMES=1000``, loop database
  ``graph.loop.max_database_keyframes=1000``); 1000 frames do not reach them, so this is how a
  session grows until its bound;
* ``small bounds``: ``SLAM_MAX_SESSION_KEYFRAMES=100`` and a 30-keyframe loop database, so the
  bounds are reached several times within the run and RSS must level off;
* ``glibc arenas``: the defaults with glibc's own malloc arena count (``SLAM_MALLOC_ARENAS=0``;
  the service caps them at 2 by default), the comparison for that setting;
* ``500-keyframe sessions``: the defaults with half the session cap (``SLAM_MAX_SESSION_KEYFRAMES=500``);
* ``no heap trim``: the defaults without the periodic ``malloc_trim`` (``SLAM_HEAP_TRIM_PERIOD_S=0``).

The number to gate on is the peak above warm-up (``rss_mib_max - rss_mib_at_warmup``): a session
grows until it rolls over, so RSS is a saw-tooth and a slope fitted to it says little.

    .venv/bin/python -m bench.slam_service_soak                  # renders a 100-frame loop
    .venv/bin/python -m bench.slam_service_soak --seq DIR --frames 1000
    # writes bench/results/slam_service_soak.json (and .md)
    .venv/bin/python -m bench.slam_service_soak --frames 3000 --configs defaults \
        --out bench/results/slam_service_soak_3000     # the shipped bounds reached (~1000 keyframes)
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.machine import command_line, describe, write_results
from metricslam_slam.supervisor.launcher import free_port
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import query_health
from metricslam_slam.tools.soak import growth_mib_per_1000_frames, soak
from metricslam_slam.zenoh_config import open_client

CONFIGS = {"defaults": {}, "small bounds": {"SLAM_MAX_SESSION_KEYFRAMES": "100",
                                            "METRICSLAM_GRAPH__LOOP__MAX_DATABASE_KEYFRAMES": "30"},
           "glibc arenas": {"SLAM_MALLOC_ARENAS": "0"}, "500-keyframe sessions": {"SLAM_MAX_SESSION_KEYFRAMES": "500"},
           "no heap trim": {"SLAM_HEAP_TRIM_PERIOD_S": "0"}}


@contextlib.contextmanager
def slam_service_child(env_overrides: dict[str, str], *args: str, start_timeout_s: float = 60.0):
    """A router on a free loopback port, a client session and a ``metricslam slam-service
    --depth-url none`` child process on it (``env_overrides`` over this environment, ``args``
    appended), answering its health query -> ``(client, process)``; all stopped at exit."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    client = open_client(endpoint)
    cmd = [sys.executable, "-m", "metricslam_cli.main", "slam-service", "--zenoh-endpoint", endpoint,
           "--depth-url", "none", "--status-period", "1", *args]
    proc = subprocess.Popen(cmd, env={**os.environ, **env_overrides}, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + start_timeout_s
        while query_health(client, 1.0) is None:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"the SLAM service did not come up (exit {proc.poll()}): {' '.join(cmd)}")
        yield client, proc
    finally:
        proc.terminate()
        proc.wait(60)
        client.close()
        router.close()


def run_config(seq_dir: Path, frames: int, env_overrides: dict[str, str], warmup_frames: int) -> dict:
    with slam_service_child(env_overrides, "--preset", "synth") as (client, proc):
        result = soak(client, seq_dir, "soak0", frames, proc.pid)
    samples = result["samples"]
    result.pop("last_status", None)
    result.update({"env": env_overrides,
        "rss_mib_start": samples[0][1], "rss_mib_at_warmup": next(r for f, r in samples if f >= warmup_frames),
        "rss_mib_end": samples[-1][1], "rss_mib_max": max(r for _, r in samples),
        "growth_mib_per_1000_frames_after_warmup": round(growth_mib_per_1000_frames(samples, warmup_frames), 1),
        "growth_mib_per_1000_frames_second_half": round(growth_mib_per_1000_frames(samples, frames // 2), 1),
        "rollovers": sum(e == "session_rolled_over" for e, _ in result["events"]),
    })
    result["peak_mib_above_warmup"] = round(result["rss_mib_max"] - result["rss_mib_at_warmup"], 1)
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seq", type=Path, help="sequence folder (default: render a 100-frame loop)")
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--warmup", type=int, default=200, help="frames before growth is measured")
    parser.add_argument("--configs", nargs="+", choices=sorted(CONFIGS), default=list(CONFIGS))
    parser.add_argument("--out", default="bench/results/slam_service_soak")
    args = parser.parse_args(argv)
    machine_before = describe()
    with tempfile.TemporaryDirectory() as tmp:
        seq = args.seq
        if seq is None:
            from metricslam.synth.scene import generate_sequence

            seq = Path(tmp) / "loop"
            generate_sequence(seq, 100, seed=3, size=(620, 188), path="loop")
        results = {name: run_config(seq, args.frames, CONFIGS[name], args.warmup) for name in args.configs}
    payload = {"command": command_line("bench.slam_service_soak", argv), "machine_before": machine_before,
               "machine_after": describe(), "sequence": str(args.seq or "rendered: 100 frames, 620x188, seed 3, loop"),
               "frames": args.frames, "warmup_frames": args.warmup, "results": results}
    rows = ["| config | RSS MiB start / after warm-up / end / max | peak above warm-up MiB "
            "| growth MiB per 1000 frames (after warm-up; 2nd half) | roll-overs | tracking | wall s |",
            "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, r in results.items():
        rows.append(f"| {name} | {r['rss_mib_start']} / {r['rss_mib_at_warmup']} / {r['rss_mib_end']} / "
                    f"{r['rss_mib_max']} | {r['peak_mib_above_warmup']} | {r['growth_mib_per_1000_frames_after_warmup']}; "
                    f"{r['growth_mib_per_1000_frames_second_half']} | {r['rollovers']} | "
                    f"{r['tracking']:.2f} | {r['wall_s']} |")
    markdown = "\n".join(["# SLAM service soak: RSS of one camera over a looped sequence", "",
        f"`{payload['command']}`", "", f"Machine before: {machine_before}", "",
        f"Machine after: {payload['machine_after']}", "", f"{args.frames} frames of {payload['sequence']}, "
        "ping-pong looped, back-pressured (2 in flight); RSS of the service process.", "", *rows, ""])
    write_results(args.out, payload, markdown)
    print(markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
