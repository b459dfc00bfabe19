"""Before/after of the depth service on the same machine: interleaved rounds, one server at a time.

Each ``--variant NAME=PYTHONPATH[,setting=value...]`` is a copy of the code (e.g. a frozen
snapshot from before a change, and ``shared``) with optional ``DepthServiceSettings`` (e.g.
``max_concurrency=3``). Every round starts each variant's server in turn (``metricslam
depth-service`` as a child, ``tests/depth_service_process.py``), warms it up and drives it with
``--clients`` keep-alive clients (``bench.depth_service_bench.run_level``) for every input and
answer form, alternating which variant goes first, so a slow spell of the shared machine hits
all alike. Inputs: ``kitti_png`` (the real KITTI PNGs of ``--frames``); with ``--jpeg-scale S``,
``jpeg_xS`` (the same frames upscaled S times and JPEG-encoded, quality 90: large camera
images); with ``--input-size W H``, ``png_WxH`` (the frames resized by the client to the network
input with ``INTER_AREA`` and PNG-encoded at compression 1: the network sees exactly the same
input as from the full-size upload). Per level: req/s, latency percentiles, the server's CPU ms per request
(``/proc``; the contention-robust number), the client's, and the load average before.

Example::

    nice -n 5 .venv/bin/python -m bench.depth_service_ab --variant before=/tmp/base \\
        --variant after=shared --frames ../shared/data/kitti_odometry/sequences/06/image_0 \\
        --jpeg-scale 2 --rounds 3 --out bench/results/depth_service_ab
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from bench.depth_service_bench import run_level
from bench.machine import command_line, describe, write_results
from tests.depth_service_process import ServiceProcess

FORMS = {"json": False, "npy": True}


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def parse_variant(spec: str) -> dict:
    name, _, rest = spec.partition("=")
    path, *pairs = rest.split(",")
    settings: dict[str, object] = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        settings[key] = value
    return {"name": name, "pythonpath": path, "settings": settings}


def inputs(frames_dir: Path, jpeg_scale: float | None,
           input_size: tuple[int, int] | None) -> dict[str, tuple[str, list[bytes]]]:
    """name -> (media type, encoded frames)."""
    pngs = [p.read_bytes() for p in sorted(frames_dir.glob("*.png"))]
    if not pngs:
        raise SystemExit(f"no PNG frames in {frames_dir}")
    out = {"kitti_png": ("image/png", pngs)}
    if input_size:  # what a client sends when it resizes to the network input itself (INTER_AREA)
        small = [cv2.resize(cv2.imdecode(np.frombuffer(d, np.uint8), cv2.IMREAD_GRAYSCALE), input_size,
                            interpolation=cv2.INTER_AREA) for d in pngs]
        out[f"png_{input_size[0]}x{input_size[1]}"] = (
            "image/png", [cv2.imencode(".png", s, [cv2.IMWRITE_PNG_COMPRESSION, 1])[1].tobytes() for s in small])
    if jpeg_scale:
        big = []
        for data in pngs:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
            img = cv2.resize(img, None, fx=jpeg_scale, fy=jpeg_scale, interpolation=cv2.INTER_LINEAR)
            big.append(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes())
        out[f"jpeg_x{jpeg_scale:g}"] = ("image/jpeg", big)
    return out


def measure(variant: dict, data: dict[str, tuple[str, list[bytes]]], forms: list[str], clients: int,
            requests: int, port: int) -> list[dict]:
    """Start the variant's server, warm it up, run every input x form once; one row each."""
    os.environ["PYTHONPATH"] = str(Path(variant["pythonpath"]).resolve())  # the child inherits it
    settings = {"max_queue": 256, "max_connections": 512, **variant["settings"]}
    rows = []
    with ServiceProcess(port, settings=settings) as service:
        for media, frames in data.values():
            run_level(port, frames, 2, True, 60, service.pid, media)  # warm-up
        for name, (media, frames) in data.items():
            for form in forms:
                load = _load()
                r = run_level(port, frames, clients, FORMS[form], requests, service.pid, media)
                rows.append({"variant": variant["name"], "input": name, "form": form, "clients": clients,
                             "requests": r.requests, "rps": r.rps, "p50_ms": r.pct(50), "p99_ms": r.pct(99),
                             "server_cpu_ms_per_req": 1e3 * r.server_cpu_s / r.requests,
                             "client_cpu_ms_per_req": 1e3 * r.client_cpu_s / r.requests,
                             "statuses": r.statuses, "load_before": load})
                print(f"{variant['name']:>8} {name:>10} {form:>4}: {r.rps:6.1f} req/s  p50 {r.pct(50):5.1f} ms  "
                      f"server CPU {rows[-1]['server_cpu_ms_per_req']:.2f} ms/req  load {load[0]:.2f}", flush=True)
    return rows


def summarize(rows: list[dict]) -> list[dict]:
    keys = sorted({(r["input"], r["form"], r["variant"]) for r in rows})
    out = []
    for inp, form, name in keys:
        sel = [r for r in rows if (r["input"], r["form"], r["variant"]) == (inp, form, name)]
        cpu = statistics.median(r["server_cpu_ms_per_req"] for r in sel)
        client = statistics.median(r["client_cpu_ms_per_req"] for r in sel)
        out.append({"input": inp, "form": form, "variant": name, "rounds": len(sel),
                    "rps_median": statistics.median(r["rps"] for r in sel),
                    "rps_min": min(r["rps"] for r in sel), "rps_max": max(r["rps"] for r in sel),
                    "p50_ms_median": statistics.median(r["p50_ms"] for r in sel),
                    "p99_ms_median": statistics.median(r["p99_ms"] for r in sel),
                    "server_cpu_ms_per_req_median": cpu, "client_cpu_ms_per_req_median": client,
                    "cpu_bound_rps": (os.cpu_count() or 1) * 1000.0 / (cpu + client),
                    "loads_before": [r["load_before"][0] for r in sel]})
    return out


def render_markdown(report: dict) -> str:
    lines = ["# Depth service before / after, interleaved", "", f"Command: ``{report['command']}``  ",
             f"Machine: {report['machine']}  ", f"Date: {report['date_utc']}  ",
             "Variants: " + "; ".join(f"`{v['name']}` = PYTHONPATH `{v['pythonpath']}`"
                                      + (f" with {v['settings']}" if v["settings"] else "") for v in report["variants"]),
             "", *[f"* {x}" for x in report["notes"]], "",
             "| input | form | variant | rounds | req/s median (min–max) | p50 ms | p99 ms | server CPU ms/req "
             "| client CPU ms/req | req/s bound from CPU | 1-min load before each |",
             "| --- | --- | --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | --- |"]
    for s in report["summary"]:
        lines.append(f"| {s['input']} | {s['form']} | {s['variant']} | {s['rounds']} | {s['rps_median']:.1f} "
                     f"({s['rps_min']:.1f}–{s['rps_max']:.1f}) | {s['p50_ms_median']:.1f} | {s['p99_ms_median']:.1f} | "
                     f"{s['server_cpu_ms_per_req_median']:.2f} | {s['client_cpu_ms_per_req_median']:.2f} | "
                     f"{s['cpu_bound_rps']:.0f} | " + ", ".join(f"{x:.2f}" for x in s["loads_before"]) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--variant", action="append", required=True, metavar="NAME=PYTHONPATH[,k=v...]")
    p.add_argument("--frames", type=Path, required=True, help="KITTI image_0 folder of PNG frames")
    p.add_argument("--jpeg-scale", type=float, default=None, help="also send the frames upscaled S times as JPEG")
    p.add_argument("--input-size", type=int, nargs=2, default=None, metavar=("W", "H"),
                   help="also send the frames resized by the client to W x H (the network input, 512 256)")
    p.add_argument("--forms", nargs="+", default=["npy", "json"], choices=list(FORMS))
    p.add_argument("--clients", type=int, default=4)
    p.add_argument("--requests", type=int, default=600, help="requests per level")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--port", type=int, default=18141)
    p.add_argument("--note", action="append", default=[])
    p.add_argument("--out", required=True, help="write OUT.json and OUT.md")
    args = p.parse_args(argv)
    variants = [parse_variant(v) for v in args.variant]
    data = inputs(args.frames, args.jpeg_scale, tuple(args.input_size) if args.input_size else None)
    report = {"command": command_line("bench.depth_service_ab", argv), "variants": variants,
              "date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "load_at_start": _load(),
              "inputs": {k: {"media_type": m, "frames": len(f), "mean_bytes": float(np.mean([len(x) for x in f]))}
                         for k, (m, f) in data.items()}, "notes": list(args.note), "rows": []}
    saved = os.environ.get("PYTHONPATH")
    try:
        for r in range(args.rounds):
            for v in (variants if r % 2 == 0 else variants[::-1]):
                report["rows"] += measure(v, data, args.forms, args.clients, args.requests, args.port)
    finally:
        if saved is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = saved
    report["summary"] = summarize(report["rows"])
    report["machine"] = describe()
    report["notes"].append(
        "The client threads run on the same 2 cores as the server. Server CPU ms per request is the "
        "contention-robust figure; 'req/s bound from CPU' = cores x 1000 / (server + client CPU ms), what the "
        "machine could do with nothing else running (derived, not measured). Loads well above 0 mean other "
        "jobs shared the cores: wall-clock req/s are then pessimistic.")
    write_results(args.out, report, render_markdown(report))
    print(f"wrote {Path(args.out).with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
