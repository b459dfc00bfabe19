"""Abuse benchmark of the depth service (issue #19 hardening): idle sockets, huge uploads, pixel bombs.

Each scenario starts a fresh service (``metricslam depth-service``, default settings) on
127.0.0.1 so one scenario's memory does not inflate the next one's baseline, and samples the
server's RSS every 50 ms from ``/proc``:

1. **idle** — 1,000 TCP connections that never send a byte, held for ``--hold-s`` (any the server
   closes is reopened every 0.5 s, so 1,000 are attempted all along); a fresh client GETs
   ``/healthz`` every 0.25 s and POSTs one real image every second. Target: health 200 in < 1 s
   throughout, RSS growth < 50 MiB.
2. **uploads** — 32 concurrent 64 MiB batch uploads (8 parts of just under 8 MiB, the largest
   batch the defaults allow), twice: parts that are valid PNG noise images, and parts with a
   valid PNG header and garbage after it (the receive path alone). Target: peak RSS growth
   < 200 MiB.
3. **bombs** — 4 clients POST a 130 kB PNG declaring 4096x4096 16-bit RGBA (128 MiB decoded) in a
   loop while one client sends real 1226x370 images; the same real client alone first, as the
   baseline. Target: real-request p99 < 200 ms.

Example (from the repository root)::

    nice -n 5 .venv/bin/python -m bench.depth_service_abuse --out bench/results/depth_service_abuse.json
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import select
import socket
import struct
import threading
import time
import zlib
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from bench.machine import command_line, describe
from metricslam_depth.settings import DepthServiceSettings
from tests.depth_service_process import ServiceProcess

FX_PX = 718.856
MIB = 2**20


# ----- measurement helpers -----

def _status_kib(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"no {key} for pid {pid}")


def rss_mib(pid: int) -> float:
    """Resident set size of ``pid``, MiB (Linux ``/proc``)."""
    return _status_kib(pid, "VmRSS") / 1024


class RssSampler(threading.Thread):
    """Peak RSS of ``pid`` from now on: the kernel's high-water mark (VmHWM, reset at start through
    ``/proc/PID/clear_refs``) and, as a cross-check, samples every ``period_s``."""

    def __init__(self, pid: int, period_s: float = 0.05) -> None:
        super().__init__(daemon=True)
        self.pid, self.period_s = pid, period_s
        self.start_mib = rss_mib(pid)
        self.peak_mib = self.start_mib
        self.hwm_reset = True
        try:
            Path(f"/proc/{pid}/clear_refs").write_text("5")
        except OSError:
            self.hwm_reset = False
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.is_set():
            self.peak_mib = max(self.peak_mib, rss_mib(self.pid))
            time.sleep(self.period_s)

    def stop(self) -> dict[str, float]:
        self._stop_event.set()
        self.join()
        end = rss_mib(self.pid)
        peak = max(self.peak_mib, _status_kib(self.pid, "VmHWM") / 1024 if self.hwm_reset else 0.0)
        return {"rss_start_mib": round(self.start_mib, 1), "rss_peak_mib": round(peak, 1),
                "rss_peak_sampled_mib": round(self.peak_mib, 1), "rss_end_mib": round(end, 1),
                "rss_peak_growth_mib": round(peak - self.start_mib, 1), "peak_from_vmhwm": self.hwm_reset}


def request(port: int, method: str, path: str, body: bytes | None = None, content_type: str | None = None,
            timeout_s: float = 30.0) -> tuple[int, float]:
    """(status, seconds) of one request on a fresh connection (status 0: transport error)."""
    headers = {"Content-Type": content_type} if content_type else {}
    t0 = time.perf_counter()
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout_s)
    try:
        conn.request(method, path, body=body, headers=headers)
        response = conn.getresponse()
        response.read()
        status = response.status
    except OSError:
        status = 0
    finally:
        conn.close()
    return status, time.perf_counter() - t0


def server_counts(port: int, route: str) -> dict[str, dict[str, float]]:
    """What the server says it answered on ``route`` and refused, from ``/metrics``."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.request("GET", "/metrics")
    text = conn.getresponse().read().decode()
    conn.close()
    answered, rejected = {}, {}
    for line in text.splitlines():
        series, _, value = line.rpartition(" ")
        if line.startswith("depth_requests_total{") and f'route="{route}"' in series:
            answered[series.split('status="')[1].split('"')[0]] = float(value)
        elif line.startswith("depth_rejected_total{"):
            rejected[series.split('reason="')[1].split('"')[0]] = float(value)
    return {"server_answered_by_status": answered, "server_rejected_by_reason": rejected}


def percentiles_ms(seconds: list[float]) -> dict[str, float]:
    if not seconds:
        return {}
    ms = np.asarray(seconds) * 1e3
    return {f"p{q}_ms": round(float(np.percentile(ms, q)), 1) for q in (50, 90, 99)} | {
        "max_ms": round(float(ms.max()), 1), "n": len(ms)}


# ----- inputs -----

def kitti_like_png(seed: int = 0) -> bytes:
    """A 1226x370 gray image with structure (the size SLAM sends), PNG-encoded."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:370, 0:1226]
    img = 80 + 100 * (y / 370) + 20 * np.sin(x / 17.0) + rng.normal(0, 8, (370, 1226))
    return cv2.imencode(".png", np.clip(img, 0, 255).astype(np.uint8))[1].tobytes()


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def png_bomb(width: int = 4096, height: int = 4096) -> bytes:
    """A valid PNG of zeros declaring ``width x height`` 16-bit RGBA: ~130 kB, 128 MiB decoded."""
    deflate = zlib.compressobj(9)
    row = bytes(1 + width * 8)
    idat = b"".join(deflate.compress(row) for _ in range(height)) + deflate.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 6, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


def batch_body(part: bytes, parts: int, boundary: str = "abuse") -> tuple[bytes, str]:
    head = (f"--{boundary}\r\nContent-Disposition: form-data; name=images; filename=x.png\r\n"
            "Content-Type: image/png\r\n\r\n").encode()
    body = b"".join(head + part + b"\r\n" for _ in range(parts)) + f"--{boundary}--\r\n".encode()
    return body, f"multipart/form-data; boundary={boundary}"


def noise_png_near(limit_bytes: int) -> bytes:
    """A gray noise PNG just under ``limit_bytes`` (noise does not compress: ~1 byte per pixel)."""
    side = int((limit_bytes * 0.995) ** 0.5)
    while True:
        data = cv2.imencode(".png", np.random.default_rng(1).integers(0, 256, (side, side), np.uint8))[1].tobytes()
        if len(data) <= limit_bytes - 1024:
            return data
        side -= 8


def garbage_png_near(limit_bytes: int) -> bytes:
    """A valid PNG signature + IHDR (2048x2048 gray) followed by random bytes up to ``limit_bytes``."""
    ihdr = _chunk(b"IHDR", struct.pack(">IIBBBBB", 2048, 2048, 8, 0, 0, 0, 0))
    head = b"\x89PNG\r\n\x1a\n" + ihdr
    return head + np.random.default_rng(2).integers(0, 256, limit_bytes - 1024 - len(head), np.uint8).tobytes()


# ----- scenarios -----

def scenario_idle(port: int, connections: int, hold_s: float) -> dict:
    legit = kitti_like_png()
    with ServiceProcess(port) as svc:
        request(port, "POST", f"/v1/disparity?fx={FX_PX}", legit, "image/png")  # warm up
        sampler = RssSampler(svc.pid)
        sampler.start()
        socks = [socket.create_connection(("127.0.0.1", port)) for _ in range(connections)]
        reopened = 0
        health, health_status, infer_status = [], Counter(), Counter()
        t_end = time.monotonic() + hold_s
        next_reopen = next_infer = time.monotonic()
        while time.monotonic() < t_end:
            status, seconds = request(port, "GET", "/healthz", timeout_s=5.0)
            health.append(seconds)
            health_status[status] += 1
            now = time.monotonic()
            if now >= next_infer:
                infer_status[request(port, "POST", f"/v1/disparity?fx={FX_PX}", legit, "image/png")[0]] += 1
                next_infer = now + 1.0
            if now >= next_reopen:  # reopen every socket the server closed: 1,000 attempted all along
                readable, _, _ = select.select(socks, [], [], 0)
                for s in readable:
                    s.close()
                    socks.remove(s)
                    socks.append(socket.create_connection(("127.0.0.1", port)))
                    reopened += 1
                next_reopen = now + 0.5
            time.sleep(0.25)
        for s in socks:
            s.close()
        memory = sampler.stop()
    return {"idle_connections": connections, "hold_s": hold_s, "reopened_after_server_close": reopened,
            "healthz": percentiles_ms(health), "healthz_statuses": dict(health_status),
            "healthz_all_200_under_1s": set(health_status) == {200} and max(health) < 1.0,
            "inference_statuses_during_hold": dict(infer_status), **memory,
            "rss_growth_target_mib": 50}


def scenario_uploads(port: int, clients: int, part: bytes, parts: int, label: str) -> dict:
    body, content_type = batch_body(part, parts)
    with ServiceProcess(port) as svc:
        request(port, "POST", f"/v1/disparity?fx={FX_PX}", kitti_like_png(), "image/png")  # warm up
        sampler = RssSampler(svc.pid)
        sampler.start()
        results: list[tuple[int, float]] = []
        lock = threading.Lock()

        def upload() -> None:
            r = request(port, "POST", f"/v1/disparity/batch?fx={FX_PX}", body, content_type, timeout_s=120)
            with lock:
                results.append(r)

        t0 = time.perf_counter()
        _run_threads(upload, clients)
        seconds = time.perf_counter() - t0
        memory = sampler.stop()
        server = server_counts(port, "/v1/disparity/batch")
    return {"parts": label, "clients": clients, "body_bytes": len(body), "part_bytes": len(part),
            "client_statuses": dict(Counter(s for s, _ in results)),
            "client_status_0_means": "the server answered early (503 upload-budget, Connection: close) "
                                     "and closed the socket while the client was still sending: reset",
            **server, "seconds": round(seconds, 2),
            "latency": percentiles_ms([t for _, t in results]), **memory, "rss_growth_target_mib": 200}


def scenario_bombs(port: int, flooders: int, duration_s: float) -> dict:
    legit, bomb = kitti_like_png(), png_bomb()
    path = f"/v1/disparity?fx={FX_PX}"
    out: dict = {"bomb_bytes": len(bomb), "bomb_declares": "4096x4096 16-bit RGBA (128 MiB decoded)",
                 "flood_clients": flooders, "duration_s": duration_s}
    with ServiceProcess(port) as svc:
        for _ in range(5):
            request(port, "POST", path, legit, "image/png")  # warm up

        def legit_loop(deadline: float, seconds: list[float], statuses: Counter) -> None:
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
            while time.monotonic() < deadline:
                t0 = time.perf_counter()
                conn.request("POST", path, body=legit, headers={"Content-Type": "image/png"})
                response = conn.getresponse()
                response.read()
                seconds.append(time.perf_counter() - t0)
                statuses[response.status] += 1
            conn.close()

        alone: list[float] = []
        alone_status: Counter = Counter()
        legit_loop(time.monotonic() + duration_s, alone, alone_status)
        out["legit_alone"] = percentiles_ms(alone) | {"statuses": dict(alone_status)}

        flooded: list[float] = []
        flooded_status, bomb_status = Counter(), Counter()
        bomb_seconds: list[float] = []
        deadline = time.monotonic() + duration_s
        lock = threading.Lock()

        def flood() -> None:
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
            while time.monotonic() < deadline:
                t0 = time.perf_counter()
                try:
                    conn.request("POST", path, body=bomb, headers={"Content-Type": "image/png"})
                    response = conn.getresponse()
                    response.read()
                    status = response.status
                except (OSError, http.client.HTTPException):
                    conn.close()
                    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
                    status = 0
                with lock:
                    bomb_seconds.append(time.perf_counter() - t0)
                    bomb_status[status] += 1
            conn.close()

        cpu0 = _cpu_s(svc.pid)
        threads = [threading.Thread(target=flood) for _ in range(flooders)]
        for t in threads:
            t.start()
        legit_loop(deadline, flooded, flooded_status)
        for t in threads:
            t.join()
        out["server_cpu_s_during_flood"] = round(_cpu_s(svc.pid) - cpu0, 2)
    out["legit_during_flood"] = percentiles_ms(flooded) | {"statuses": dict(flooded_status)}
    out["bombs"] = percentiles_ms(bomb_seconds) | {"statuses": dict(bomb_status),
                                                   "per_s": round(len(bomb_seconds) / duration_s, 1)}
    out["legit_p99_target_ms"] = 200
    return out


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def training_processes() -> int:
    """How many ``metricslam train`` processes share the machine right now (Linux ``/proc``)."""
    count = 0
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            args = cmdline.read_bytes().split(b"\0")
        except OSError:
            continue
        count += any(a.endswith(b"metricslam") for a in args) and b"train" in args
    return count


def _run_threads(target: Callable[[], None], n: int) -> None:
    threads = [threading.Thread(target=target) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--port", type=int, default=18120)
    parser.add_argument("--connections", type=int, default=1000)
    parser.add_argument("--hold-s", type=float, default=60.0, help="how long the idle sockets are held")
    parser.add_argument("--uploaders", type=int, default=32)
    parser.add_argument("--bomb-s", type=float, default=20.0, help="duration of each bomb phase")
    parser.add_argument("--out", type=Path, default=Path("bench/results/depth_service_abuse.json"))
    args = parser.parse_args(argv)

    defaults = DepthServiceSettings()
    payload: dict = {
        "command": command_line("bench.depth_service_abuse", argv),
        "machine": describe(),
        "note": "2-core development machine shared with a training job (the load average above; "
                "training_processes counts `metricslam train` processes at the start); client and "
                "server run on the same 2 cores, so latencies include client CPU",
        "training_processes": training_processes(),
        "niceness": os.nice(0),
        "server_settings": "defaults: " + json.dumps(
            {k: v for k, v in defaults.model_dump(mode="json").items() if k not in {"host", "port"}}),
    }
    print(payload["machine"], flush=True)
    payload["idle"] = scenario_idle(args.port, args.connections, args.hold_s)
    print("idle:", json.dumps(payload["idle"]), flush=True)
    part_limit = defaults.max_body_bytes - 512  # + part headers: the batch stays under its limit
    payload["uploads"] = [
        scenario_uploads(args.port + 1, args.uploaders, garbage_png_near(part_limit), defaults.max_batch,
                         "PNG header + random bytes (received in full, refused at decode)"),
        scenario_uploads(args.port + 2, args.uploaders, noise_png_near(part_limit), defaults.max_batch,
                         "valid gray noise PNGs (decoded and inferred)"),
    ]
    for u in payload["uploads"]:
        print("uploads:", json.dumps(u), flush=True)
    payload["bombs"] = scenario_bombs(args.port + 3, 4, args.bomb_s)
    print("bombs:", json.dumps(payload["bombs"]), flush=True)
    payload["machine_after"] = describe()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(payload, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
