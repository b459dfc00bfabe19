"""Are the depth network's stereo training labels biased by range? SGBM labels vs LiDAR.

Reads a training cache built by ``metricslam train`` (``runs/depth_cache/<seq>_HxW_..._ndNNN.npz``:
``bm_left``, the left SGBM disparity as a fraction of the full width, resized to the network's
input) for a KITTI raw drive that also has projected LiDAR (``depth_0/``), and compares each
LiDAR point's depth with the label's depth at the same (resized) pixel, per LiDAR range bin.
1.00 everywhere means the labels teach the right depth at every range.

Example::

    .venv/bin/python -m bench.diagnostics.label_bias \\
        --cache runs/depth_cache/2011_09_26_drive_0013_256x512_s1_nd192.npz \\
        --seq ../shared/data/kitti_raw_stereo/sequences/2011_09_26_drive_0013 --out bench/results/label_bias_0013
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from bench.machine import command_line, describe, write_results
from metricslam.datasets import open_sequence

BINS_M = ((2, 5), (5, 10), (10, 20), (20, 40), (40, 60), (60, 80))


def label_over_lidar(cache: Path, seq_dir: Path, step: int = 4) -> dict:
    labels = np.load(cache)["bm_left"]  # (N, H, W) d_frac of the full width
    seq = open_sequence(seq_dir)
    fxb = seq.camera.fx_px * seq.baseline_m
    width = seq.camera.width_px
    files = sorted((seq_dir / "depth_0").glob("*.png"))
    ratios, depths = [], []
    for i in range(0, min(len(files), labels.shape[0]), step):
        depth_m = cv2.imread(str(files[i]), cv2.IMREAD_UNCHANGED).astype(np.float32) / 256.0
        ys, xs = np.nonzero(depth_m > 0)
        h, w = depth_m.shape
        lab = labels[i, (ys * labels.shape[1] / h).astype(int), (xs * labels.shape[2] / w).astype(int)]
        ok = lab > 0
        ratios.append((fxb / (lab[ok] * width)) / depth_m[ys, xs][ok])  # label depth / LiDAR depth
        depths.append(depth_m[ys, xs][ok])
    r, d = np.concatenate(ratios), np.concatenate(depths)
    return {f"{lo}-{hi}": {"n": int(((d >= lo) & (d < hi)).sum()),
                           "label_over_lidar": float(np.median(r[(d >= lo) & (d < hi)]))
                           if ((d >= lo) & (d < hi)).any() else None} for lo, hi in BINS_M}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cache", type=Path, required=True)
    p.add_argument("--seq", type=Path, required=True)
    p.add_argument("--out", metavar="PREFIX")
    args = p.parse_args(argv)
    bins = label_over_lidar(args.cache, args.seq)
    command = command_line("bench.diagnostics.label_bias", argv)
    lines = ["# SGBM training labels vs LiDAR, by range (bench/diagnostics/label_bias.py)", "",
             f"Command: `{command}`  ", f"Machine: {describe()}", "",
             "| LiDAR depth | points | label depth / LiDAR depth (median) |", "| --- | --- | --- |"]
    lines += [f"| {k} m | {v['n']} | " + ("–" if v["label_over_lidar"] is None else f"×{v['label_over_lidar']:.3f}")
              + " |" for k, v in bins.items()]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        write_results(args.out, {"command": command, "machine": describe(), "bins": bins}, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
