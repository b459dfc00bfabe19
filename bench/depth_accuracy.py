"""Metric accuracy of the depth network (onnxruntime), against honest references.

1. ``kitti_raw_lidar``: projected LiDAR depth of the left colour camera. Models trained with
   ``depth_frames`` on part of it (``training/configs/experiments/train_depth_lidar*.yaml``: frames 26-77) must be
   scored on the rest only: ``--lidar-frames 0:20``.
2. A KITTI odometry stereo sequence held out of training (default 06): SGBM depth
   (left-right checked, full resolution) on textured pixels.

For each reference pixel the model's L3 inverse depth is sampled bilinearly
(:func:`metricslam.depth.sample_map`) and inverted. Metrics over pixels with reference depth in
``[min_depth_m, max_depth_m]``: median of pred/true, abs-rel, RMSE (m), δ<1.25. Beside the
model, the trivial **flat-road prior**: a ground plane ``camera_height_m`` below the camera
(depth by image row ``v``: ``fy·h/(v − cy)`` below the horizon, ``max_depth_m`` above it).

Example::

    .venv/bin/python -m bench.depth_accuracy --data ../shared/data \\
        --model shared/metricslam/models/depth_l3.onnx --out bench/results/depth_accuracy
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import cv2
import numpy as np

from bench.machine import command_line
from metricslam.camera import PinholeCamera
from metricslam.datasets.kitti import KittiOdometry
from metricslam.datasets import open_sequence
from metricslam.depth import DepthModel, sample_map
from metricslam.stereo import block_matching_pair  # the matcher of the training labels


def metrics(pred_m: np.ndarray, true_m: np.ndarray) -> dict[str, float]:
    """Standard single-image depth metrics over matched samples (both (N,) metres)."""
    ratio = pred_m / true_m
    return {"median_ratio": float(np.median(ratio)), "abs_rel": float(np.mean(np.abs(pred_m - true_m) / true_m)),
            "rmse_m": float(np.sqrt(np.mean((pred_m - true_m) ** 2))),
            "delta_1_25": float(np.mean(np.maximum(ratio, 1 / ratio) < 1.25)), "n_pixels": int(true_m.size)}


def flat_road_depth(v_px: np.ndarray, fy_px: float, cy_px: float, camera_height_m: float,
                    max_depth_m: float) -> np.ndarray:
    """Depth of a ground plane ``camera_height_m`` below the camera at image rows ``v_px``."""
    dv = v_px - cy_px
    with np.errstate(divide="ignore"):
        z = np.where(dv > 0, fy_px * camera_height_m / np.maximum(dv, 1e-9), max_depth_m)
    return np.clip(z, 1e-3, max_depth_m)


def predict_at(model: DepthModel, image: np.ndarray, camera: PinholeCamera, uv_px: np.ndarray,
               max_depth_m: float) -> np.ndarray:
    inv = model.predict_inv_depth(image, camera=camera)  # v1 models use camera.fx_px only
    inv_at = sample_map(inv.inv_depth_per_m, uv_px, (inv.image_width_px, inv.image_height_px))
    return np.clip(1.0 / np.maximum(inv_at, 1.0 / max_depth_m), 1e-3, max_depth_m)


def l3_oracle_depth(true_m: np.ndarray, uv_px: np.ndarray, image_size: tuple[int, int],
                    grid_hw: tuple[int, int], max_depth_m: float) -> np.ndarray:
    """The reference's own depth seen through the network's output grid: the mean reference
    inverse depth of each (h, w) cell (empty cells: the nearest filled one), sampled back with
    the same bilinear :func:`sample_map`. An upper bound for ANY model with this output size —
    what remains is the error of a coarse map at depth edges — not a competitor (it uses the truth).
    """
    from scipy.ndimage import distance_transform_edt

    h, w = grid_hw
    width_px, height_px = image_size
    col = np.clip((uv_px[:, 0] * w / width_px).astype(int), 0, w - 1)
    row = np.clip((uv_px[:, 1] * h / height_px).astype(int), 0, h - 1)
    total, count = np.zeros((h, w)), np.zeros((h, w))
    np.add.at(total, (row, col), 1.0 / true_m)
    np.add.at(count, (row, col), 1.0)
    grid = np.where(count > 0, total / np.maximum(count, 1), 0.0)
    _, (ri, ci) = distance_transform_edt(count == 0, return_indices=True)
    grid = grid[ri, ci]
    inv_at = sample_map(grid, uv_px, image_size)
    return np.clip(1.0 / np.maximum(inv_at, 1.0 / max_depth_m), 1e-3, max_depth_m)


#: range bins (m) of the per-bin medians: where the scale factors sample the network, bin by bin
RANGE_BINS_M = ((1.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 80.0))


def per_range_bin(pred_m: np.ndarray, true_m: np.ndarray) -> dict[str, dict]:
    """Median pred/true and abs-rel per reference-depth bin (:data:`RANGE_BINS_M`), keyed "lo-hi"."""
    out = {}
    for lo, hi in RANGE_BINS_M:
        sel = (true_m >= lo) & (true_m < hi)
        if sel.sum() >= 20:
            out[f"{lo:g}-{hi:g}"] = metrics(pred_m[sel], true_m[sel])
    return out


def evaluate_lidar(model: DepthModel, folder: Path, args) -> dict:
    """Projected LiDAR of a KITTI raw colour folder (``image_02``/``depth_02``) or of a KITTI-layout
    sequence with ``depth_0`` (e.g. ``kitti_raw_stereo/sequences/2011_09_26_drive_0013``)."""
    seq = open_sequence(folder)
    cam = seq.camera
    preds, flats, oracles, trues, per_frame = [], [], [], [], []
    grid_hw = (model.contract.output_height, model.contract.output_width)
    first, stop = args.lidar_frames
    for i in range(first, min(stop if stop is not None else len(seq), len(seq)), args.frame_step):
        frame = seq[i]
        if frame.depth_m is None:
            continue
        v, u = np.nonzero((frame.depth_m >= args.min_depth_m) & (frame.depth_m <= args.max_depth_m))
        true = frame.depth_m[v, u].astype(np.float64)
        uv = np.stack([u, v], 1).astype(np.float64)
        pred = predict_at(model, frame.image, cam, uv, args.max_depth_m)
        flat = flat_road_depth(v.astype(float), cam.fy_px, cam.cy_px, args.camera_height_m, args.max_depth_m)
        size = (frame.image.shape[1], frame.image.shape[0])
        oracles.append(l3_oracle_depth(true, uv, size, grid_hw, args.max_depth_m))
        preds.append(pred), flats.append(flat), trues.append(true)
        per_frame.append(float(np.median(pred / true)))
    pred, flat, oracle, true = (np.concatenate(x) for x in (preds, flats, oracles, trues))
    return {"folder": str(folder), "frames": len(per_frame), "model": metrics(pred, true),
            "flat_road": metrics(flat, true), "l3_oracle": metrics(oracle, true),
            **slam_range(pred, flat, true, args.slam_min_depth_m), "model_by_range": per_range_bin(pred, true),
            "per_frame_median_ratio": {"mean": float(np.mean(per_frame)), "std": float(np.std(per_frame))}}


def slam_range(pred_m: np.ndarray, flat_m: np.ndarray, true_m: np.ndarray, min_depth_m: float) -> dict:
    """The same metrics over reference depths ≥ ``min_depth_m``: the range where the SLAM's scale
    factors sample the network (VO landmarks; median ~21 m on KITTI 06), which the full-set
    numbers (dominated by near pixels in urban scenes) can hide."""
    far = true_m >= min_depth_m
    if not far.any():
        return {}
    return {"model_far": metrics(pred_m[far], true_m[far]), "flat_road_far": metrics(flat_m[far], true_m[far])}


def sgbm_depth(left: np.ndarray, right: np.ndarray, fx_px: float, baseline_m: float,
               texture_min: float) -> np.ndarray:
    """Full-res SGBM depth (m), 0 where invalid, untextured, or failing the left-right check."""
    d_left, _ = block_matching_pair(left, right)
    gx = cv2.Sobel(left, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(left, cv2.CV_32F, 0, 1, ksize=3)
    textured = np.hypot(gx, gy) >= texture_min
    ok = (d_left > 0) & textured
    return np.where(ok, fx_px * baseline_m / np.maximum(d_left, 1e-6), 0.0)


def evaluate_stereo(model: DepthModel, seq_dir: Path, args) -> dict:
    seq = KittiOdometry(seq_dir)
    cam = seq.camera
    preds, flats, oracles, trues = [], [], [], []
    grid_hw = (model.contract.output_height, model.contract.output_width)
    for i in range(0, len(seq), args.frame_step):
        frame = seq[i]
        ref = sgbm_depth(frame.image, frame.image_right, cam.fx_px, frame.baseline_m, args.texture_min)
        v, u = np.nonzero((ref >= args.min_depth_m) & (ref <= args.max_depth_m))
        true = ref[v, u]
        uv = np.stack([u, v], 1).astype(np.float64)
        preds.append(predict_at(model, frame.image, cam, uv, args.max_depth_m))
        flats.append(flat_road_depth(v.astype(float), cam.fy_px, cam.cy_px, args.camera_height_m, args.max_depth_m))
        oracles.append(l3_oracle_depth(true, uv, (ref.shape[1], ref.shape[0]), grid_hw, args.max_depth_m))
        trues.append(true)
    pred, flat, oracle, true = (np.concatenate(x) for x in (preds, flats, oracles, trues))
    return {"sequence": seq_dir.name, "frames": len(preds), "model": metrics(pred, true),
            "flat_road": metrics(flat, true), "l3_oracle": metrics(oracle, true), **slam_range(pred, flat, true, args.slam_min_depth_m)}


def _table(rows: list[tuple[str, dict]], slam_min_depth_m: float) -> str:
    lines = ["| set | method | median pred/true | abs-rel | RMSE (m) | δ<1.25 | pixels |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    labels = {"model": "model", "flat_road": "flat_road",
              "l3_oracle": "L3 oracle: the reference itself on the 32x64 output grid (bound for any L3 model)",
              "model_far": f"model, depth ≥ {slam_min_depth_m:g} m (SLAM range)",
              "flat_road_far": f"flat_road, depth ≥ {slam_min_depth_m:g} m"}
    for name, res in rows:
        for method in (k for k in labels if k in res):
            m = res[method]
            lines.append(f"| {name} | {labels[method]} | {m['median_ratio']:.3f} | {m['abs_rel']:.3f} | {m['rmse_m']:.2f} | "
                         f"{m['delta_1_25']:.3f} | {m['n_pixels']} |")
    return "\n".join(lines)


def _range_table(label: str, res: dict) -> str:
    bins = res.get("model_by_range", {})
    head = "| " + label + " | " + " | ".join(f"{b} m" for b in bins) + " |"
    rule = "| --- |" + " --- |" * len(bins)
    med = "| model median pred/true | " + " | ".join(f"{m['median_ratio']:.3f}" for m in bins.values()) + " |"
    rel = "| model abs-rel | " + " | ".join(f"{m['abs_rel']:.3f}" for m in bins.values()) + " |"
    n = "| pixels | " + " | ".join(str(m["n_pixels"]) for m in bins.values()) + " |"
    return "\n".join([head, rule, med, rel, n])


def _frame_range(text: str) -> tuple[int, int | None]:
    first, _, stop = text.partition(":")
    try:
        return int(first or 0), (int(stop) if stop else None)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected FIRST:STOP (e.g. 0:20), got {text!r}") from exc


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="../shared/data", help="the shared data folder")
    p.add_argument("--model", help="ONNX model (default: shipped)")
    p.add_argument("--stereo-seq", default="06", help="held-out KITTI odometry sequence ('' to skip)")
    p.add_argument("--lidar", default="kitti_raw_lidar",
                   help="LiDAR folder under --data (kitti_raw_lidar, or a KITTI-layout sequence with depth_0/ "
                        "such as kitti_raw_stereo/sequences/2011_09_26_drive_0013)")
    p.add_argument("--frame-step", type=int, default=1)
    p.add_argument("--lidar-frames", type=_frame_range, default=(0, None), metavar="FIRST:STOP",
                   help="score LiDAR frames FIRST <= i < STOP only (default all; '0:20' is the part "
                        "training/configs/experiments/train_depth_lidar*.yaml keep out of training)")
    p.add_argument("--min-depth-m", type=float, default=1.0)
    p.add_argument("--max-depth-m", type=float, default=80.0)
    p.add_argument("--camera-height-m", type=float, default=1.65)
    p.add_argument("--slam-min-depth-m", type=float, default=10.0,
                   help="also report reference depths >= this (the range SLAM samples; default 10)")
    p.add_argument("--texture-min", type=float, default=40.0, help="Sobel magnitude for 'textured' pixels")
    p.add_argument("--out", help="write OUT.md and OUT.json")
    args = p.parse_args(argv)
    data = Path(args.data)
    model = DepthModel.load(args.model, threads=1)
    results = {"command": command_line("bench.depth_accuracy", argv), "model_id": model.contract.model_id, "weights_precision": model.contract.weights_precision,
               "training_data": model.contract.training_data, "lidar": evaluate_lidar(model, data / args.lidar, args)}
    first, stop = args.lidar_frames
    lidar_name = Path(args.lidar).name
    lidar_label = f"{lidar_name} (LiDAR)" if (first, stop) == (0, None) else \
        f"{lidar_name} frames {first}..{'end' if stop is None else stop - 1} (LiDAR)"
    rows = [(lidar_label, results["lidar"])]
    if args.stereo_seq:
        results["stereo"] = evaluate_stereo(model, data / "kitti_odometry" / "sequences" / args.stereo_seq, args)
        rows.append((f"KITTI {args.stereo_seq} (SGBM, textured)", results["stereo"]))
    table = _table(rows, args.slam_min_depth_m) + "\n\n" + _range_table(lidar_label, results["lidar"])
    print(table)
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.with_suffix(".json").write_text(json.dumps(results, indent=2))
        machine = f"{platform.machine()}, {platform.processor() or 'cpu'}, python {platform.python_version()}"
        out.with_suffix(".md").write_text(
            f"# Depth accuracy\n\nCommand: `{command_line('bench.depth_accuracy', argv)}`\n\n"
            f"Machine: {machine}. Model: `{model.contract.model_id}` ({model.contract.weights_precision}), trained on: {model.contract.training_data}.\n"
            f"Depth range {args.min_depth_m}–{args.max_depth_m} m; flat road = plane {args.camera_height_m} m "
            f"below the camera.\n\n{table}\n\nLiDAR per-frame median ratio: mean "
            f"{results['lidar']['per_frame_median_ratio']['mean']:.3f} ± "
            f"{results['lidar']['per_frame_median_ratio']['std']:.3f} over {results['lidar']['frames']} frames.\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
