"""onnxruntime latency of the depth model: ms per image at 1 and 2 threads.

Times two things per thread count: the network alone on a preprocessed (1, 1, H, W) input, and
the whole ``DepthModel.predict_inv_depth`` call on a KITTI-sized gray image (resize, normalize,
run, convert). Median and 90th percentile over ``--repeats`` runs after ``--warmup``.

Example::

    .venv/bin/python -m bench.depth_speed --out bench/results/depth_speed
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from bench.machine import command_line
from metricslam.camera import PinholeCamera
from metricslam.depth import DepthModel


def _time(fn, warmup: int, repeats: int) -> dict[str, float]:
    for _ in range(warmup):
        fn()
    samples, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        samples.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    # CPU time per call: on a contended machine wall time includes waiting for a core; for one
    # thread, CPU time is close to the wall time on an idle core.
    return {"median_ms": float(np.median(samples)), "p90_ms": float(np.percentile(samples, 90)),
            "cpu_median_ms": float(np.median(cpu))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", help="ONNX model (default: shipped)")
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--repeats", type=int, default=100)
    p.add_argument("--out", help="write OUT.md and OUT.json")
    args = p.parse_args(argv)
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (370, 1226), dtype=np.uint8)
    # KITTI odometry 06's camera (a contract-version-2 model needs all of it; version 1 reads fx only)
    camera = PinholeCamera(fx_px=707.0, fy_px=707.0, cx_px=601.9, cy_px=183.1, width_px=1226, height_px=370)
    results = {}
    for threads in args.threads:
        model = DepthModel.load(args.model, threads=threads)
        x = model.preprocess([image], [camera])
        session, c = model._session, model.contract  # noqa: SLF001 — timing the bare network
        net = _time(lambda session=session, c=c, x=x: session.run([c.output_name], {c.input_name: x}),
                    args.warmup, args.repeats)
        full = _time(lambda model=model: model.predict_inv_depth(image, camera=camera), args.warmup, args.repeats)
        results[str(threads)] = {"network": net, "predict_inv_depth_1226x370": full}
    c = model.contract
    lines = ["| threads | network median (ms) | network p90 | network CPU time median (ms) | "
             "predict_inv_depth median (ms) | p90 | CPU time median |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for threads, r in results.items():
        full = r["predict_inv_depth_1226x370"]
        lines.append(f"| {threads} | {r['network']['median_ms']:.2f} | {r['network']['p90_ms']:.2f} | "
                     f"{r['network']['cpu_median_ms']:.2f} | {full['median_ms']:.2f} | {full['p90_ms']:.2f} | "
                     f"{full['cpu_median_ms']:.2f} |")
    table = "\n".join(lines)
    print(table)
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        load = os.getloadavg()
        machine = (f"{platform.machine()}, {os.cpu_count()} CPUs, python {platform.python_version()}, "
                   f"load average at the end {load[0]:.2f} (this run itself adds about 1)")
        command = command_line("bench.depth_speed", argv)
        out.with_suffix(".json").write_text(json.dumps({"command": command, "model_id": c.model_id,
                                                        "weights_precision": c.weights_precision,
                                                        "input": [c.input_height, c.input_width],
                                                        "machine": machine, "results": results}, indent=2))
        out.with_suffix(".md").write_text(f"# Depth model speed (onnxruntime, CPU)\n\nCommand: `{command}`\n\n"
            f"Machine: {machine}.\nModel `{c.model_id}` ({c.weights_precision}), input {c.input_height}x{c.input_width}, output "
            f"{c.output_height}x{c.output_width}, {c.params} parameters. {args.repeats} runs after {args.warmup} warm-up.\n\n"
            f"{table}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
