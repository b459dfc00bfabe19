"""Benchmark the depth service over HTTP: req/s and latency percentiles, JSON vs binary, and a soak.

Starts the real service (``metricslam depth-service``) on 127.0.0.1, loads KITTI-size PNG frames
from a KITTI odometry sequence (``--media pgm``: the same gray pixels as binary PGM;
``--media pgm-input``: as binary PGM resized to the model's input with ``fx`` scaled, what the SLAM
service uploads for a contract-version-1 model), and drives it with keep-alive ``http.client`` connections, one
thread per concurrent client (the client is cheap so that most CPU goes to the server; client and
server still share the machine, which the report says).

Example::

    .venv/bin/python -m bench.depth_service_bench \\
        --frames /work/shared/data/kitti_odometry/sequences/06/image_0 \\
        --out bench/results/depth_service.md
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from bench.machine import command_line, describe
from metricslam_slam.service.http_depth import PGM_MEDIA_TYPE, encode_pgm
from tests.depth_service_process import ServiceProcess

FX_PX = 718.856
#: --media -> Content-Type of the uploads
MEDIA_TYPES = {"png": "image/png", "pgm": PGM_MEDIA_TYPE, "pgm-input": PGM_MEDIA_TYPE}
MEDIA_WORDS = {"png": "the PNG files", "pgm": "binary PGM (`image/x-portable-graymap`)",
               "pgm-input": "binary PGM resized to the model's input with fx scaled (the SLAM service's uploads)"}


@dataclass
class RunResult:
    """Outcome of one load level."""

    clients: int
    form: str
    requests: int
    seconds: float
    latencies_ms: list[float] = field(default_factory=list)
    statuses: dict[int, int] = field(default_factory=dict)
    server_cpu_s: float = 0.0
    client_cpu_s: float = 0.0

    @property
    def rps(self) -> float:
        return self.requests / self.seconds

    def pct(self, q: float) -> float:
        return float(np.percentile(self.latencies_ms, q))


def rss_mib(pid: int) -> float:
    """Resident set size of ``pid`` in MiB (Linux ``/proc``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


def cpu_seconds(pid: int) -> float:
    """User + system CPU time consumed so far by ``pid`` (Linux ``/proc``), seconds."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _client(port: int, frames: list[bytes], binary: bool, count: int, offset: int,
            latencies: list[float], statuses: dict[int, int], lock: threading.Lock,
            media_type: str = "image/png", fx_px: float = FX_PX) -> None:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    headers = {"Content-Type": media_type}
    if binary:
        headers["Accept"] = "application/x-npy"
    mine: list[float] = []
    codes: dict[int, int] = {}
    for i in range(count):
        body = frames[(offset + i) % len(frames)]
        t0 = time.perf_counter()
        conn.request("POST", f"/v1/disparity?fx={fx_px!r}", body=body, headers=headers)
        response = conn.getresponse()
        response.read()
        mine.append((time.perf_counter() - t0) * 1e3)
        codes[response.status] = codes.get(response.status, 0) + 1
    conn.close()
    with lock:
        latencies.extend(mine)
        for code, n in codes.items():
            statuses[code] = statuses.get(code, 0) + n


def run_level(port: int, frames: list[bytes], clients: int, binary: bool, total: int,
              server_pid: int, media_type: str = "image/png", fx_px: float = FX_PX) -> RunResult:
    """``total`` requests split over ``clients`` concurrent keep-alive connections."""
    per_client = max(1, total // clients)
    latencies: list[float] = []
    statuses: dict[int, int] = {}
    lock = threading.Lock()
    threads = [threading.Thread(target=_client, args=(port, frames, binary, per_client, k * 7, latencies, statuses,
                                                      lock, media_type, fx_px)) for k in range(clients)]
    server_cpu0, client_cpu0 = cpu_seconds(server_pid), time.process_time()
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    seconds = time.perf_counter() - t0
    return RunResult(clients, "npy" if binary else "json", per_client * clients, seconds, latencies, statuses,
                     cpu_seconds(server_pid) - server_cpu0, time.process_time() - client_cpu0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=Path, required=True,
                        help="folder of KITTI PNG frames, e.g. .../kitti_odometry/sequences/06/image_0")
    parser.add_argument("--port", type=int, default=18110)
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 4, 16])
    parser.add_argument("--requests", type=int, default=1000, help="requests per load level")
    parser.add_argument("--soak", type=int, default=10_000, help="requests in the soak (0 = skip)")
    parser.add_argument("--soak-clients", type=int, default=4)
    parser.add_argument("--threads", type=int, default=None, help="DEPTH_THREADS for the server")
    parser.add_argument("--max-concurrency", type=int, default=None, help="DEPTH_MAX_CONCURRENCY")
    parser.add_argument("--batch-window-ms", type=float, default=None, help="DEPTH_BATCH_WINDOW_MS (micro-batching)")
    parser.add_argument("--media", choices=sorted(MEDIA_TYPES), default="png",
                        help="upload the frames as PNG files (as read) or as binary PGM of the same pixels")
    parser.add_argument("--out", type=Path, default=None, help="write the markdown report here")
    parser.add_argument("--json", type=Path, default=None, help="write raw numbers as JSON here")
    args = parser.parse_args(argv)
    paths = sorted(args.frames.glob("*.png"))
    if not paths:
        print(f"no PNG frames in {args.frames}; pass --frames to a KITTI image_0 folder", file=sys.stderr)
        return 1
    frames = [p.read_bytes() for p in paths]
    import cv2
    shape = cv2.imdecode(np.frombuffer(frames[0], np.uint8), cv2.IMREAD_UNCHANGED).shape
    media_type = MEDIA_TYPES[args.media]
    gray = [cv2.imdecode(np.frombuffer(f, np.uint8), cv2.IMREAD_GRAYSCALE) for f in frames]
    if args.media == "pgm":
        frames = [encode_pgm(g) for g in gray]
    fx_px = FX_PX
    server_settings: dict[str, object] = {"max_queue": 256, "max_connections": 512}
    for key in ("threads", "max_concurrency", "batch_window_ms"):
        if getattr(args, key) is not None:
            server_settings[key] = getattr(args, key)
    load_before = os.getloadavg()
    results: list[RunResult] = []
    soak: dict[str, object] = {}
    with ServiceProcess(args.port, settings=server_settings) as service:
        conn = http.client.HTTPConnection("127.0.0.1", args.port, timeout=30)
        conn.request("GET", "/v1/model")
        contract = json.loads(conn.getresponse().read())
        server_settings["model"] = contract["model_id"]
        conn.close()
        if args.media == "pgm-input":  # as HttpDepthSource uploads to a version-1 model
            size = (contract["input_width"], contract["input_height"])
            frames = [encode_pgm(cv2.resize(g, size, interpolation=cv2.INTER_AREA)) for g in gray]
            fx_px = FX_PX * size[0] / shape[1]
        run_level(args.port, frames, 2, True, 100, service.pid, media_type, fx_px)  # warm up (first-call allocations, caches)
        rss_start = rss_mib(service.pid)
        for clients in args.clients:
            for binary in (False, True):
                r = run_level(args.port, frames, clients, binary, args.requests, service.pid, media_type, fx_px)
                results.append(r)
                print(f"{clients:>3} clients {r.form:>4}: {r.rps:7.1f} req/s  p50 {r.pct(50):6.1f} ms  "
                      f"p99 {r.pct(99):6.1f} ms  server CPU {r.server_cpu_s / r.requests * 1e3:.1f} ms/req  "
                      f"statuses {r.statuses}", flush=True)
        if args.soak:
            rss_before = rss_mib(service.pid)
            samples = [(0, rss_before)]
            step = max(1, args.soak // 10)
            done, soak_statuses, soak_lat = 0, {}, []
            t0 = time.perf_counter()
            while done < args.soak:
                r = run_level(args.port, frames, args.soak_clients, done % (2 * step) == 0, step, service.pid,
                              media_type, fx_px)
                done += r.requests
                soak_lat.extend(r.latencies_ms)
                for code, n in r.statuses.items():
                    soak_statuses[code] = soak_statuses.get(code, 0) + n
                samples.append((done, rss_mib(service.pid)))
            soak = {"requests": done, "clients": args.soak_clients, "seconds": time.perf_counter() - t0,
                    "rss_before_mib": rss_before, "rss_after_mib": samples[-1][1], "rss_samples": samples,
                    "statuses": soak_statuses, "p50_ms": float(np.percentile(soak_lat, 50)),
                    "p99_ms": float(np.percentile(soak_lat, 99))}
            print(f"soak {done} requests: RSS {rss_before:.1f} -> {samples[-1][1]:.1f} MiB, statuses {soak_statuses}")
    load_after = os.getloadavg()
    command = command_line("bench.depth_service_bench", argv)
    report = render(results, soak, command, shape, len(frames), server_settings, rss_start, load_before, load_after,
                    args.media)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(report)
        print(f"wrote {args.out}")
    if args.json:
        raw = {"media": args.media, "media_type": media_type, "load_average_before": list(load_before),
               "load_average_after": list(load_after), "levels": [{"clients": r.clients, "form": r.form, "requests": r.requests, "rps": r.rps,
                           "p50_ms": r.pct(50), "p90_ms": r.pct(90), "p99_ms": r.pct(99),
                           "server_cpu_ms_per_req": r.server_cpu_s / r.requests * 1e3,
                           "client_cpu_ms_per_req": r.client_cpu_s / r.requests * 1e3,
                           "statuses": r.statuses} for r in results], "soak": soak}
        args.json.write_text(json.dumps(raw, indent=2))
    return 0


def render(results: list[RunResult], soak: dict, command: str, shape: tuple, n_frames: int,
           server_settings: dict, rss_start: float, load_before: tuple, load_after: tuple, media: str = "png") -> str:
    lines = ["# Depth service benchmark", "", f"Command: `{command}`", "",
        f"Machine: {describe()}. 1-min load average {load_before[0]:.2f} before the run "
        f"and {load_after[0]:.2f} after (a load before well above 0 means other jobs competed, "
        "and the numbers are pessimistic); the client runs on the same 2 cores as the server.", "",
        f"Input: {n_frames} real KITTI frames ({shape[1]}x{shape[0]} gray) sent as {MEDIA_WORDS[media]}, "
        "POST /v1/disparity, "
        f"keep-alive connections, one thread per client. Server: `metricslam depth-service` with "
        f"{', '.join(f'DEPTH_{k.upper()}={v}' for k, v in server_settings.items() if k != 'model')} "
        f"(other settings default), serving model `{server_settings.get('model')}`.", "",
        "| clients | form | requests | req/s | p50 ms | p90 ms | p99 ms | server CPU ms/req | client CPU ms/req | statuses |",
        "| ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    cpu_ms = float(np.mean([r.server_cpu_s / r.requests * 1e3 for r in results])) if results else float("nan")
    for r in results:
        lines.append(f"| {r.clients} | {r.form} | {r.requests} | {r.rps:.1f} | {r.pct(50):.1f} | "
                     f"{r.pct(90):.1f} | {r.pct(99):.1f} | {r.server_cpu_s / r.requests * 1e3:.1f} | "
                     f"{r.client_cpu_s / r.requests * 1e3:.1f} | {r.statuses} |")
    if results:
        lines += ["", f"Server CPU per request is the contention-robust number: {cpu_ms:.1f} ms on average, so a "
                  f"server with all {os.cpu_count()} cores to itself could not exceed about "
                  f"{os.cpu_count() * 1000 / cpu_ms:.0f} req/s here (an upper bound derived from CPU time, "
                  "not a measurement; CPU time itself is inflated by the sharing)."]
    if soak:
        lines += ["", f"## Soak: {soak['requests']} requests, {soak['clients']} clients, JSON and npy alternating "
                  f"per {soak['requests'] // 10}", "",
                  f"Server RSS {soak['rss_before_mib']:.1f} MiB before -> {soak['rss_after_mib']:.1f} MiB after "
                  f"({soak['seconds']:.0f} s, p50 {soak['p50_ms']:.1f} ms, p99 {soak['p99_ms']:.1f} ms, statuses "
                  f"{soak['statuses']}). RSS after warm-up, before the load levels: {rss_start:.1f} MiB.", "",
                  "RSS every 10 %: " + ", ".join(f"{n}: {m:.1f}" for n, m in soak["rss_samples"]) + " (requests: MiB)"]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
