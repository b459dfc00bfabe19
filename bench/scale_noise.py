"""Measure the two noise levels the global graph's scale fusion rests on, on a VALIDATION drive.

1. **VO scale drift** (``GraphConfig.odom_sigma_log_scale``): the local VO alone (``metricslam run
   --vo-only``) against ground truth. The log of the local scale (estimated / true length of
   every 20-frame window) is treated as a random walk: the variance of its change over a lag of
   k frames grows like ``k·q``; ``q`` times the frames per keyframe is the per-keyframe variance.
2. **Network scale error** (``GraphConfig.scale_sigma_floor_log``): per image, the median of
   ``log(z_true / z_net)`` over textured pixels 5–60 m away (the range VO landmarks live in),
   from the rendered ``depth_0``; its standard deviation and its integrated autocorrelation
   length ``τ`` along the drive. ``N`` keyframes carry about ``N / τ_kf`` independent scale
   measurements, so each keyframe's factor gets ``sd·√τ_kf``.

Use a rendered drive that is NOT a benchmark sequence, e.g.::

    metricslam synth /tmp/val05 --frames 2000 --seed 505 \\
        --trajectory ../shared/data/kitti_gt_poses_full/05.txt --size 620x188
    .venv/bin/python -m bench.scale_noise --seq /tmp/val05 --out bench/results/scale_noise
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
from bench.machine import command_line, describe, write_results
from metricslam.datasets import open_sequence
from metricslam.depth import DepthModel, sample_map
from metricslam.trajectory.io import read_kitti_poses

WINDOW_FRAMES = 20
LAGS_FRAMES = (20, 50, 100, 200, 400, 800)


def vo_drift(gt_path: Path, est_path: Path, n_keyframes: int) -> dict:
    """Random-walk rate of the VO's log local scale (see module docstring)."""
    gt, est = read_kitti_poses(gt_path), read_kitti_poses(est_path)
    n = min(len(gt), len(est))
    p_gt, p_est = gt[:n, :3, 3], est[:n, :3, 3]
    true_len = np.linalg.norm(p_gt[WINDOW_FRAMES:] - p_gt[:-WINDOW_FRAMES], axis=1)
    est_len = np.linalg.norm(p_est[WINDOW_FRAMES:] - p_est[:-WINDOW_FRAMES], axis=1)
    log_s = np.where(true_len > 5.0, np.log(np.maximum(est_len, 1e-9) / np.maximum(true_len, 1e-9)), np.nan)
    rows = []
    for k in LAGS_FRAMES:
        if k >= len(log_s):
            break
        d = log_s[k:] - log_s[:-k]
        d = d[np.isfinite(d)]
        rows.append({"lag_frames": k, "var": float(np.var(d)), "var_per_frame": float(np.var(d) / k)})
    q = float(np.median([r["var_per_frame"] for r in rows]))
    frames_per_kf = n / max(n_keyframes, 1)
    return {"frames": n, "keyframes": n_keyframes, "frames_per_keyframe": frames_per_kf, "lags": rows,
            "var_per_frame": q, "sigma_log_scale_per_keyframe": float(np.sqrt(q * frames_per_kf))}


def network_error(seq_dir: Path, model: DepthModel, step: int, frames_per_kf: float) -> dict:
    """Per-image network log scale error, its spread and correlation length (module docstring)."""
    seq = open_sequence(str(seq_dir), load_right=False)  # loads depth_0 into Frame.depth_m
    errs = []
    for i in range(0, len(seq), step):
        frame = seq[i]
        if frame.depth_m is None:
            raise SystemExit(f"{seq_dir} has no depth_0/: use a `metricslam synth` drive")
        z_true = frame.depth_m.astype(np.float64)
        grad = np.hypot(cv2.Sobel(frame.image, cv2.CV_32F, 1, 0), cv2.Sobel(frame.image, cv2.CV_32F, 0, 1))
        v, u = np.nonzero((z_true >= 5.0) & (z_true <= 60.0) & (grad > 40.0))
        if len(u) < 50:
            continue
        inv = model.predict_inv_depth(frame.image, camera=seq.camera)
        inv_at = sample_map(inv.inv_depth_per_m, np.stack([u, v], 1).astype(float),
                            (inv.image_width_px, inv.image_height_px))
        errs.append(float(np.median(np.log(inv_at * z_true[v, u]))))
    e = np.array(errs)
    x = e - e.mean()
    tau_images = 1.0
    for k in range(1, len(x) // 2):
        rho = float(np.mean(x[:-k] * x[k:]) / np.mean(x * x))
        if rho <= 0:
            break
        tau_images += 2.0 * rho
    tau_kf = tau_images * step / frames_per_kf
    return {"images": len(e), "image_step": step, "mean_log_error": float(e.mean()), "sd_log_error": float(e.std()),
            "tau_frames": tau_images * step, "tau_keyframes": tau_kf,
            "sigma_per_keyframe_factor": float(e.std() * np.sqrt(tau_kf))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", required=True, type=Path, help="rendered validation drive (metricslam synth)")
    p.add_argument("--model", action="append", default=[], help="ONNX model(s) (default: the shipped one)")
    p.add_argument("--vo-est", type=Path, help="existing --vo-only estimate + its stats JSON beside it (.json)")
    p.add_argument("--image-step", type=int, default=2)
    p.add_argument("--out", help="write OUT.md and OUT.json")
    args = p.parse_args(argv)

    est, stats = args.vo_est, args.vo_est.with_suffix(".json") if args.vo_est else None
    if est is None:
        tmp = Path(tempfile.mkdtemp(prefix="scale_noise_"))
        est, stats = tmp / "vo.txt", tmp / "vo.json"
        subprocess.run([sys.executable, "-m", "metricslam_cli.main", "run", str(args.seq), "--vo-only",
                        "--no-progress", "--out", str(est), "--json", str(stats)], check=True)
    drift = vo_drift(args.seq / "poses" / "00.txt", est, json.loads(stats.read_text())["keyframes"])
    nets = {}
    for m in args.model or [None]:
        model = DepthModel.load(m, threads=1)
        nets[m or "default"] = {"model_id": model.contract.model_id,
                                **network_error(args.seq, model, args.image_step, drift["frames_per_keyframe"])}
    lines = ["| lag (frames) | var of Δ log scale | per frame |", "| --- | --- | --- |"]
    lines += [f"| {r['lag_frames']} | {r['var']:.5f} | {r['var_per_frame']:.2e} |" for r in drift["lags"]]
    vo_line = (f"VO: {drift['frames']} frames, {drift['keyframes']} keyframes "
               f"({drift['frames_per_keyframe']:.2f} frames/keyframe) → **odometry log-scale sigma "
               f"{drift['sigma_log_scale_per_keyframe']:.4f} per keyframe**.")
    lines += ["", vo_line, "",
              "| model | images | mean log(z_true/z_net) | sd | τ (frames) | τ (keyframes) | factor sigma sd·√τ_kf |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {k} (`{v['model_id']}`) | {v['images']} | {v['mean_log_error']:+.4f} | {v['sd_log_error']:.4f} | "
              f"{v['tau_frames']:.1f} | {v['tau_keyframes']:.1f} | **{v['sigma_per_keyframe_factor']:.3f}** |"
              for k, v in nets.items()]
    table = "\n".join(lines)
    print(table)
    if args.out:
        command = command_line("bench.scale_noise", argv)
        md = (f"# Scale noise: VO drift and network error on a validation drive\n\nCommand: `{command}`  \n"
              f"Machine: {describe()}\n\n{table}\n")
        write_results(args.out, {"command": command, "vo_drift": drift, "network": nets}, md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
