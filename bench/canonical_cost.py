"""What the canonical camera (depth contract v2) costs per image: v1 vs v2 ``predict_inv_depth``.

The same network twice — the shipped float32 model (contract v1: whole-image resize) and a copy
whose metadata says contract v2 (``bench.canonical_invariance.write_metadata_as_v2``: warp to the
canonical focal, crop/pad, map back) — timed on one real frame of a drive, one inference thread,
interleaved runs. The difference is the v2 pre/post-processing alone (issue #17: within 10 %).

Example::

    .venv/bin/python -m bench.canonical_cost --seq ../shared/data/kitti_raw_stereo/sequences/2011_09_26_drive_0013 \\
        --out bench/results/canonical_cost
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from bench.canonical_invariance import write_metadata_as_v2
from bench.machine import command_line, describe, write_results
from metricslam.datasets import open_sequence
from metricslam.depth import FLOAT32_MODEL_PATH, DepthModel


def time_model(model: DepthModel, image: np.ndarray, camera, repeats: int, warmup: int = 20) -> list[float]:
    for _ in range(warmup):
        model.predict_inv_depth(image, camera=camera)
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        model.predict_inv_depth(image, camera=camera)
        out.append(1e3 * (time.perf_counter() - t0))
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", required=True, help="sequence folder (its middle frame is timed)")
    p.add_argument("--repeats", type=int, default=300)
    p.add_argument("--rounds", type=int, default=2, help="interleaved rounds per model")
    p.add_argument("--v2-copy", default="runs/canonical_invariance/shipped_as_v2.onnx")
    p.add_argument("--out", metavar="PREFIX")
    args = p.parse_args(argv)
    seq = open_sequence(args.seq)
    frame = seq[len(seq) // 2]
    v2_path = Path(args.v2_copy)
    if not v2_path.is_file():
        write_metadata_as_v2(FLOAT32_MODEL_PATH, v2_path)
    models = {"v1 (whole-image resize)": DepthModel.load(FLOAT32_MODEL_PATH, threads=1),
              "v2 (canonical camera)": DepthModel.load(v2_path, threads=1)}
    times: dict[str, list[float]] = {k: [] for k in models}
    for _ in range(args.rounds):
        for name, model in models.items():
            times[name] += time_model(model, frame.image, seq.camera, args.repeats)
    rows = {k: {"median_ms": float(np.median(v)), "p90_ms": float(np.percentile(v, 90)), "n": len(v)}
            for k, v in times.items()}
    v1, v2 = (r["median_ms"] for r in rows.values())
    command = command_line("bench.canonical_cost", argv)
    lines = ["# Cost of the canonical camera per image (bench/canonical_cost.py)", "",
             f"Command: `{command}`  ", f"Machine: {describe()}  ",
             f"Frame: {args.seq} #{len(seq) // 2}, {frame.image.shape[1]}x{frame.image.shape[0]}; float32 "
             "`depth_l3.onnx` and its v2-metadata copy, 1 inference thread", "",
             "| contract | median ms | p90 ms | runs |", "| --- | --- | --- | --- |"]
    lines += [f"| {k} | {r['median_ms']:.2f} | {r['p90_ms']:.2f} | {r['n']} |" for k, r in rows.items()]
    lines += ["", f"v2 / v1: ×{v2 / v1:.3f} (target: within 10 %)."]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        write_results(args.out, {"command": command, "machine": describe(), "rows": rows, "v2_over_v1": v2 / v1},
                      text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
