"""Does a depth model fit its labels, on the drives it was trained on and on unseen ones?

For every training cache given (``runs/depth_cache/<seq>_HxW_..._ndNNN.npz`` from ``metricslam
train``: the 256x512 left images and ``bm_left``, the SGBM disparity as a fraction of the full
width for the training baseline) and every model, the model is run on the cached left images and
its L3 output compared with the label reduced to the same grid (per-cell median of the valid
values, cells at least half valid — the SGBM oracle of ``bench/landmark_depth.py``), per range bin
of the label's depth: ``d_net / d_label``, median over cells. One table row per (model, drive).

A row near ×1.00 on a drive the model was trained on and far from it on an unseen one is a
generalization gap; far from it on a training drive is a fitting limit (loss, capacity, labels).
Depth is ``fx·B / (d_frac·W)`` with the cache's ``fx_px``, the training baseline 0.537 m and
the drive's full width (KITTI 1241/1242 px; the ratio does not depend on it).

Example::

    .venv/bin/python -m bench.diagnostics.label_fit --model shared/metricslam/models/depth_l3_int8.onnx \\
        --cache runs/depth_cache/kitti01_256x512_s1_off-1.77px_nd192.npz \\
        --cache runs/depth_cache/2011_09_26_drive_0013_256x512_s1_nd192.npz --out /tmp/label_fit
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bench.machine import command_line, describe, write_results
from metricslam.depth import DepthModel

BINS_M = ((2.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 60.0), (60.0, np.inf))
BIN_LABELS = tuple(f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">{lo:g}" for lo, hi in BINS_M)
TRAIN_BASELINE_M = 0.537
FULL_WIDTH_PX = 1241.0


def cell_labels(bm: np.ndarray, grid_hw: tuple[int, int], min_valid: float = 0.5) -> np.ndarray:
    """(N, H, W) sparse d_frac labels (0 = none) -> (N, h, w) per-cell median, NaN where < min_valid."""
    n, H, W = bm.shape
    h, w = grid_hw
    fy, fx = H // h, W // w
    cells = bm.reshape(n, h, fy, w, fx).transpose(0, 1, 3, 2, 4).reshape(n, h, w, fy * fx).astype(np.float32)
    valid = cells > 0
    out = np.full((n, h, w), np.nan, np.float32)
    keep = valid.mean(-1) >= min_valid
    masked = np.where(valid, cells, np.nan)
    out[keep] = np.nanmedian(masked[keep], axis=-1)
    return out


def fit_by_range(model: DepthModel, cache: Path) -> dict:
    """Per label-depth bin: cells and median d_net/d_label for one cache."""
    z = np.load(cache)
    c = model.contract
    labels = cell_labels(z["bm_left"], (c.output_height, c.output_width))
    pred = np.stack([model.predict_d_frac([img])[0] for img in z["left"]])
    depth_m = float(z["fx_px"]) * TRAIN_BASELINE_M / (labels * FULL_WIDTH_PX)
    ratio = labels / pred  # d_net / d_label
    out = {}
    for (lo, hi), label in zip(BINS_M, BIN_LABELS, strict=True):
        m = (depth_m >= lo) & (depth_m < hi) & np.isfinite(ratio)
        out[label] = {"cells": int(m.sum()), "net_over_label": float(np.median(ratio[m])) if m.any() else None}
    return {"drive": str(z["name"]), "frames": int(labels.shape[0]), "bins": out}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", action="append", required=True, help="ONNX depth model (repeat)")
    p.add_argument("--cache", action="append", type=Path, required=True, help="training cache .npz (repeat)")
    p.add_argument("--out", metavar="PREFIX")
    args = p.parse_args(argv)
    rows = []
    for model_path in args.model:
        model = DepthModel.load(model_path)
        rows += [{"model": model_path, **fit_by_range(model, cache)} for cache in args.cache]
    command = command_line("bench.diagnostics.label_fit", argv)
    lines = ["# Depth model vs its SGBM labels on the L3 grid, by label range (bench/diagnostics/label_fit.py)",
             "", f"Command: `{command}`  ", f"Machine: {describe()}", "",
             "| model | drive | " + " | ".join(f"{b} m" for b in BIN_LABELS) + " |",
             "| --- | --- |" + " --- |" * len(BIN_LABELS)]
    for r in rows:
        cells = ["–" if v["net_over_label"] is None else f"×{v['net_over_label']:.2f}" for v in r["bins"].values()]
        lines.append(f"| `{Path(r['model']).name}` | {r['drive']} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        write_results(args.out, {"command": command, "machine": describe(), "rows": rows}, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
