"""What the SLAM's scale factors actually consume, against the truth at the same landmarks.

Runs the system of ``metricslam run --deterministic`` in-process (the one session builder, the
preset ``metricslam run`` picks, the given or shipped depth model) and subscribes to the back
end's :class:`~metricslam.slam.events.ScaleMeasured` events: for every keyframe, the landmarks
the back end turned into scale measurements ``s_j = ξ_j / z_j`` (VO inverse depth over the
network's metric inverse depth). Each landmark is then given a reference depth that uses
neither the network nor the VO:

* ``stereo`` — the keyframe's own stereo pair, left-right-checked full-resolution SGBM
  (:func:`metricslam.stereo.block_matching_pair`, 192 disparities), median valid disparity in a
  5x5 window, ``d = fx·B / disparity`` (m);
* ``lidar`` (a check of the reference, where the folder has ``depth_0/``): projected LiDAR, 5x5
  median of valid pixels.

Reported per sequence:

1. **per range bin of the reference depth** (2–5, 5–10, 10–20, 20–40, 40–60, >60 m): how many of
   the SLAM's measurements fall there (fraction), the network's median ``d_net / d_ref`` there
   (what a scale factor in that bin is off by), and the VO's own relative depth error there
   (``ξ_j·d_ref`` over its keyframe's median; 1 = the VO's structure is right at that range);
2. **per keyframe**: the back end's robust estimate from its measurements (Huber, as the graph
   uses it) over the truth ``k_true`` = median ``ξ_j·d_ref`` (m per keyframe VO unit), and the final
   optimized keyframe scale over ``k_true``; medians over keyframes. These two say whether the
   learned measurements explain the trajectory's scale error and by which ranges.

Example::

    .venv/bin/python -m bench.scale_measurements \\
        --seq ../shared/data/kitti_raw_stereo/sequences/2011_09_26_drive_0013 \\
        --seq ../shared/data/kitti_odometry/sequences/06 --out bench/results/scale_measurements
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from bench.machine import command_line, publish
from bench.scale_upper_bound import disparity_at
from metricslam.datasets import open_sequence
from metricslam.depth import DEFAULT_MODEL_PATH
from metricslam.geometry.sim3 import scale as sim3_scale
from metricslam.slam.events import ScaleMeasured
from metricslam.slam.graph.scale_factor import robust_log_scale
from metricslam.slam.session_builder import build_session, preset_for
from metricslam.slam.system_config import SystemConfig
from metricslam.stereo import block_matching_pair

#: reference-depth bins (m), lo <= d < hi
BINS_M = ((2.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 60.0), (60.0, np.inf))
BIN_LABELS = tuple(f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">{lo:g}" for lo, hi in BINS_M)
NUM_DISPARITIES = 192


def _lidar_at(depth_png: Path, uv_px: np.ndarray) -> np.ndarray:
    raw = cv2.imread(str(depth_png), cv2.IMREAD_UNCHANGED)
    if raw is None:
        return np.full(len(uv_px), np.nan)
    d = raw.astype(np.float32) / 256.0
    return disparity_at(d, uv_px)  # same 5x5 valid median, on depth instead of disparity


def run_and_record(seq_dir: str | Path, model_path: str | Path | None,
                   depth_source: object | None = None) -> tuple[list, dict, dict]:
    """Run the deterministic system on ``seq_dir`` (depth from ``depth_source``, else the ONNX
    model ``model_path``, else the shipped one); return its ScaleMeasured events, the optimized
    keyframe poses (frame -> (4, 4) Sim(3)) and the run's stats."""
    seq = open_sequence(seq_dir)
    overrides = {"vo": {"preset": preset_for(seq_dir)}, "deterministic": True}
    if model_path is not None:
        overrides["depth"] = {"model_path": str(model_path)}
    session = build_session(seq.camera, SystemConfig(**overrides), depth_source=depth_source)
    events: list[ScaleMeasured] = []
    session.backend.events.subscribe(events.append, ScaleMeasured)
    for i in range(len(seq)):
        session.process(seq[i])
    session.close()
    return events, session.backend.optimized_keyframe_poses(), session.stats()


def reference_depths(seq_dir: str | Path, events: list[ScaleMeasured]) -> list[dict]:
    """Per keyframe event: landmark arrays restricted to the measured ones, with reference depths."""
    seq = open_sequence(seq_dir, load_right=True)
    fxb = seq.camera.fx_px * seq.baseline_m
    depth_dir = Path(seq_dir) / "depth_0"
    out = []
    for ev in events:
        if ev.error or ev.scales.size == 0:
            continue
        xi, z = ev.landmarks_inv_depth, ev.net_inv_depth_per_m
        with np.errstate(divide="ignore", invalid="ignore"):
            s = xi / z
        used = np.isin(s, ev.scales)  # the landmarks whose ξ/z the graph received
        uv = ev.landmarks_uv_px[used]
        frame = seq[ev.frame_index]
        disp = block_matching_pair(frame.image, frame.image_right, NUM_DISPARITIES)[0]
        d_stereo = fxb / disparity_at(disp, uv)
        png = depth_dir / f"{ev.frame_index:06d}.png"
        d_lidar = _lidar_at(png, uv) if png.is_file() else np.full(len(uv), np.nan)
        out.append({"frame": ev.frame_index, "xi": xi[used], "d_net": 1.0 / z[used], "scales": ev.scales,
                    "d_stereo": d_stereo, "d_lidar": d_lidar})
    return out


def _median(x: np.ndarray) -> float | None:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else None


def analyse(per_kf: list[dict], poses: dict, ref: str, sigma_log: float, huber_k: float) -> dict:
    """Bins and per-keyframe ratios of the module docstring against reference ``ref``."""
    d_all, r_net, r_vo, kf_rows = [], [], [], []
    for kf in per_kf:
        d_ref = kf[f"d_{ref}"]
        ok = np.isfinite(d_ref) & (d_ref > 0)
        if ok.sum() < 5:
            continue
        k_true = float(np.median(kf["xi"][ok] * d_ref[ok]))
        d_all.append(d_ref[ok])
        r_net.append(kf["d_net"][ok] / d_ref[ok])
        r_vo.append(kf["xi"][ok] * d_ref[ok] / k_true)
        k_meas = float(np.exp(robust_log_scale(kf["scales"], sigma_log, huber_k)[0]))
        S = poses.get(kf["frame"])
        kf_rows.append({"frame": kf["frame"], "n": int(ok.sum()), "k_true": k_true,
                        "measured_over_true": k_meas / k_true,
                        "optimized_over_true": None if S is None else sim3_scale(S) / k_true})
    if not kf_rows:
        return {"keyframes": 0}
    d, rn, rv = np.concatenate(d_all), np.concatenate(r_net), np.concatenate(r_vo)
    bins = {}
    for (lo, hi), label in zip(BINS_M, BIN_LABELS, strict=True):
        m = (d >= lo) & (d < hi)
        bins[label] = {"n": int(m.sum()), "fraction": float(m.mean()),
                       "net_over_ref": _median(rn[m]), "vo_over_ref": _median(rv[m])}
    opt = [r["optimized_over_true"] for r in kf_rows if r["optimized_over_true"] is not None]
    return {"keyframes": len(kf_rows), "landmarks": int(d.size), "median_ref_depth_m": float(np.median(d)),
            "net_over_ref_all": _median(rn), "bins": bins,
            "measured_over_true_median": _median([r["measured_over_true"] for r in kf_rows]),
            "optimized_over_true_median": _median(opt), "per_keyframe": kf_rows}


def evaluate(seq_dirs: list[str], model_path: str | None, depth_source: object | None = None) -> dict:
    """The module docstring's report for each sequence folder (JSON-ready)."""
    config = SystemConfig().graph_config()
    out = {"model": str(model_path or os.path.relpath(DEFAULT_MODEL_PATH)), "sequences": {}}
    if depth_source is not None:
        out["model"] = type(depth_source).__name__
    for seq_dir in seq_dirs:
        t0 = time.perf_counter()
        events, poses, stats = run_and_record(seq_dir, model_path, depth_source)
        per_kf = reference_depths(seq_dir, events)
        res = {"seq_dir": seq_dir, "keyframe_events": len(events), "wall_s": None}
        for ref in ("stereo", "lidar"):
            if any(np.isfinite(kf[f"d_{ref}"]).any() for kf in per_kf):
                res[ref] = analyse(per_kf, poses, ref, config.scale_sigma_log, config.scale_huber_k)
        res["wall_s"] = time.perf_counter() - t0
        out["sequences"][Path(seq_dir).name] = res
    return out


def markdown(result: dict, command: str, machine: str) -> str:
    lines = ["# Scale measurements: what the SLAM's scale factors consume (bench/scale_measurements.py)", "",
             f"Command: `{command}`  ", f"Machine: {machine}  ", f"Model: `{result['model']}`", ""]
    for name, res in result["sequences"].items():
        for ref in ("stereo", "lidar"):
            a = res.get(ref)
            if not a or not a.get("keyframes"):
                continue
            lines += [f"## {name}, reference: {ref}", "",
                      f"{a['keyframes']} keyframes, {a['landmarks']} measured landmarks (median reference depth "
                      f"{a['median_ref_depth_m']:.1f} m). Per keyframe, median over keyframes: back end's "
                      f"measured scale / true ×{a['measured_over_true_median']:.3f}; final optimized / true ×"
                      + (f"{a['optimized_over_true_median']:.3f}" if a["optimized_over_true_median"] else "–")
                      + ".", "",
                      "| reference depth | fraction of measurements | network d_net/d_ref | VO ξ·d_ref / keyframe median |",
                      "| --- | --- | --- | --- |"]
            for label, b in a["bins"].items():
                def f(x):
                    return "–" if x is None else f"×{x:.3f}"
                lines.append(f"| {label} m | {100 * b['fraction']:.1f} % ({b['n']}) | {f(b['net_over_ref'])} "
                             f"| {f(b['vo_over_ref'])} |")
            lines.append("")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", action="append", required=True, help="KITTI-layout stereo folder (repeat)")
    p.add_argument("--model", default=None, help="ONNX depth model (default: the shipped one)")
    p.add_argument("--out", metavar="PREFIX", help="write PREFIX.json and PREFIX.md")
    args = p.parse_args(argv)
    cv2.setNumThreads(1)
    command = command_line("bench.scale_measurements", argv)
    result = evaluate(args.seq, args.model)
    publish(args.out, result, command, markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
