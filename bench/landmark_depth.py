"""Landmark depth: is the depth network right where the VO's corners are, range bin by range bin?

The primary selection metric for depth models. The SLAM samples the network only at the
corners the VO tracks (scale factors ``ξ_j / z_j``), so this scores the network there, against a
reference that uses neither the network nor the VO: corners triangulated with ground-truth motion.

Per sequence with ground-truth poses (``T_world_cam0``, KITTI 3x4 lines), for frames
``i = 0, stride, 2·stride, …`` (default stride 3) and ``j = i + gap`` (default gap 3):

1. Corners of frame ``i`` (``cv2.goodFeaturesToTrack``: up to 1000, quality 0.01, min distance
   7 px) are tracked towards frame ``j`` with pyramidal KLT frame by frame (``i → i+1 → … → j``;
   each step must pass a forward-backward check, backward track back within 1 px). A corner lost
   on the way keeps its last good frame ``i < k ≤ j``: near corners (5–10 m) change scale too
   fast to survive 3 frames of forward motion, and one-shot ``i → j`` tracking kept none of them
   on KITTI 06 (the chain keeps 500+; they need less baseline anyway).
2. Each track is triangulated (``cv2.triangulatePoints``) with the ground-truth relative motion
   ``T_cam_k_cam_i`` (poses ``T_world_cam0``) and the intrinsics. Kept: reprojection error < 1 px
   in both frames, in front of both cameras, depth in frame ``i`` within 2–60 m, and a parallax angle of at least
   ``--min-parallax-deg`` (default 1°; without it, corners near the focus of expansion or pairs
   where the car stands still triangulate to depths that reprojection cannot reject).
   That depth ``z_tri`` (m) is the reference.
3. **network** — the depth model's inverse-depth map of frame ``i`` (1/m, its output grid, e.g.
   32x64) sampled bilinearly at the corners (:func:`metricslam.depth.sample_map`),
   ``z_net = 1 / ξ_net`` (m). Score: ``z_net / z_tri`` (1 = right, 0.9 = 10 % too near).
4. **oracle** — the same for the stereo pair's own depth seen through the network's grid: the
   left-right-checked full-resolution SGBM of the pair (:func:`metricslam.stereo.block_matching_pair`,
   the matcher of the training labels; 192 disparities by default, i.e. down to 2 m on KITTI),
   median disparity per cell of the network's grid (a cell needs ≥ 10 % valid pixels, else NaN
   and its corners are left out; ``pool_cells`` of ``bench/scale_upper_bound.py``, as its
   ``stereo`` variant), inverse depth ``d / (fx·B)`` (1/m), sampled the same way. What a perfect
   student of the SGBM labels at this resolution would score — a model-free ceiling that also
   exposes a biased stereo pair (KITTI 01's disparity offset).
5. Per range bin of ``z_tri`` — 2–5, 5–10, 10–20, 20–40, 40–60 m, and all — the number of
   corners, the median of ``z/z_tri`` and its 25th / 75th percentiles. Where the sequence has a
   depth map (``depth_0/``: KITTI raw projected LiDAR, ``metricslam synth``'s rendered depth), a
   **check** row scores that map at the corners (5x5 median of valid pixels) against ``z_tri``:
   it tests the reference, not the network (0013: 1.0 ± 4 % per bin; rendered: ± 1 %).

KITTI's road is below the image bottom nearer than ~6 m, so the 2–5 m bin is usually empty.

:func:`summary` reduces a result to one number per sequence for model selection:
``worst_abs_log_ratio`` = the largest ``|log median(z_net/z_tri)|`` over the bins 5–10, 10–20,
20–40, 40–60 m that hold ≥ 20 corners (0.05 ≈ 5 % off in the worst bin).

``--slam`` adds, per sequence, where the SLAM itself puts its scale landmarks: the same system as
``metricslam run --deterministic`` (same model; VO preset chosen as ``metricslam run`` does,
which gives KITTI raw 0013 the ``synth`` preset because of its ``depth_0/``) runs in-process;
for every marginalized keyframe the landmarks the back end turns into scale measurements (VO
inverse depth ``ξ_j > 0``, network inverse depth within the graph's ``[min_inv_depth_per_m,
max_inv_depth_per_m]``; the even subsample to ``max_scale_landmarks`` per keyframe is not
mimicked) get their metric depth as the SLAM estimates it,
``s_kf / ξ_j`` (``s_kf``: the keyframe's final optimized Sim(3) scale, m per keyframe VO unit),
and are histogrammed into the same bins (fraction of all such landmarks; ``<2`` and ``>60``
hold the rest). ``vo_weighted_abs_log_ratio`` in :func:`summary` weights each bin's
``|log median ratio|`` by that fraction.

The SGBM oracle is cached per (sequence, frame) in memory (:data:`_ORACLE_CACHE`), so several
models scored in one process share it. Single-threaded (OpenCV and onnxruntime).

Example::

    .venv/bin/python -m bench.landmark_depth \\
        --seq /work/shared/data/kitti_odometry/sequences/06 --gt /work/shared/data/kitti_odometry/poses/06.txt \\
        --seq /work/shared/data/kitti_raw_stereo/sequences/2011_09_26_drive_0013 \\
        --gt /work/shared/data/kitti_raw_stereo/poses/2011_09_26_drive_0013.txt \\
        --slam --out bench/results/landmark_depth
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
from metricslam.datasets import open_sequence
from metricslam.depth import DEFAULT_MODEL_PATH, DepthModel, sample_map
from metricslam.slam.session_builder import preset_for
from metricslam.stereo import block_matching_pair
from bench.gt_corners import intrinsics, track_corners, triangulate_gt
from bench.scale_upper_bound import disparity_at, pool_cells
from bench.slam_landmarks import scale_landmark_depths

#: range bins of the triangulated depth (m), lo <= z < hi (the last one includes 60 m)
RANGE_BINS_M = ((2.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 60.0))
BIN_LABELS = tuple(f"{lo:g}-{hi:g}" for lo, hi in RANGE_BINS_M)
#: the bins :func:`summary` takes the worst of (the near bin is left out: few scale landmarks)
SUMMARY_BINS = ("5-10", "10-20", "20-40", "40-60")
#: a bin needs this many corners to count in :func:`summary`
SUMMARY_MIN_CORNERS = 20

#: SGBM oracle maps (1/m on the network grid) by (sequence folder, frame, grid, disparities)
_ORACLE_CACHE: dict[tuple, np.ndarray] = {}


def oracle_inv_depth(seq, index: int, grid_hw: tuple[int, int], num_disparities: int = 192,
                     min_valid_fraction: float = 0.1) -> np.ndarray:
    """(h, w) SGBM inverse depth (1/m) of frame ``index`` on the grid ``grid_hw``: median valid
    disparity per cell / (fx·B), NaN where fewer than ``min_valid_fraction`` of a cell's pixels
    (at least 10) are valid. Cached in memory per (sequence, frame, grid, disparities)."""
    key = (str(Path(getattr(seq, "seq_dir", seq.name)).resolve()), int(index), tuple(grid_hw),
           int(num_disparities), float(min_valid_fraction))
    if key not in _ORACLE_CACHE:
        frame = seq[index]
        disp = block_matching_pair(frame.image, frame.image_right, num_disparities)[0]
        h, w = grid_hw
        n_px = (disp.shape[0] // h) * (disp.shape[1] // w)
        cells = pool_cells(disp, tuple(grid_hw), min_valid=max(10, int(n_px * min_valid_fraction)), empty=np.nan)
        _ORACLE_CACHE[key] = cells.astype(np.float64) / (seq.camera.fx_px * seq.baseline_m)
    return _ORACLE_CACHE[key]


def ratio_stats(ratio: np.ndarray) -> dict:
    """``n``, ``median``, ``p25``, ``p75`` of finite ratios (None statistics when empty)."""
    r = np.asarray(ratio, float)
    r = r[np.isfinite(r)]
    if r.size == 0:
        return {"n": 0, "median": None, "p25": None, "p75": None}
    p25, med, p75 = np.percentile(r, [25, 50, 75])
    return {"n": int(r.size), "median": float(med), "p25": float(p25), "p75": float(p75)}


def bin_index(z_m: np.ndarray) -> np.ndarray:
    """(N,) index into :data:`RANGE_BINS_M` of each depth, -1 outside 2–60 m."""
    z = np.asarray(z_m, float)
    out = np.full(z.shape, -1, int)
    for k, (lo, hi) in enumerate(RANGE_BINS_M):
        last = k == len(RANGE_BINS_M) - 1
        out[(z >= lo) & ((z <= hi) if last else (z < hi))] = k
    return out


def per_bin(z_ref_m: np.ndarray, z_est_m: np.ndarray) -> dict[str, dict]:
    """:func:`ratio_stats` of ``z_est / z_ref`` per bin of ``z_ref`` (keys :data:`BIN_LABELS`) and
    over all (``"all"``). Non-finite estimates (no valid oracle cell) are left out."""
    z_ref = np.asarray(z_ref_m, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.asarray(z_est_m, float) / z_ref
    idx = bin_index(z_ref)
    out = {label: ratio_stats(ratio[idx == k]) for k, label in enumerate(BIN_LABELS)}
    out["all"] = ratio_stats(ratio[idx >= 0])
    return out


def landmark_samples(seq, model: DepthModel, stride: int = 3, gap: int = 3, min_parallax_deg: float = 1.0,
                     num_disparities: int = 192, oracle: bool = True) -> dict[str, np.ndarray]:
    """Corners triangulated with ground truth and both depth estimates at them, pooled over frames.

    Returns:
        ``{"frame", "u", "v", "z_tri", "z_net", "z_oracle", "z_depth0"}``, each (N,), depths in
        metres: ``z_oracle`` NaN where its cell is empty (everywhere when ``oracle`` is False);
        ``z_depth0`` the sequence's own depth map (``depth_0/``: projected LiDAR, or the rendered
        depth of ``metricslam synth``) at the corner, median of the valid pixels in a 5x5 window
        (NaN without one) — a check of the triangulated reference, not of the network. Plus
        ``"pairs"``, the number of frame pairs used.
    """
    T_world = seq.T_world_cam_gt
    if T_world is None:
        raise ValueError(f"{seq.name}: needs ground-truth poses (--gt)")
    if oracle and seq.baseline_m is None:
        raise ValueError(f"{seq.name}: the oracle needs the right images (image_1/)")
    cam = seq.camera
    K = intrinsics(cam)
    cols = {k: [] for k in ("frame", "u", "v", "z_tri", "z_net", "z_oracle", "z_depth0")}
    pairs = 0
    for i in range(0, len(seq) - gap, stride):
        a = seq[i]
        uv_a, uv_end, steps = track_corners([a.image] + [seq[i + k].image for k in range(1, gap + 1)])
        keep, z = np.zeros(len(uv_a), bool), np.zeros(len(uv_a))
        for k in np.unique(steps):
            m = steps == k
            keep[m], z[m] = triangulate_gt(uv_a[m], uv_end[m], K, np.linalg.inv(T_world[i + k]) @ T_world[i],
                                           min_parallax_deg=min_parallax_deg)
        pairs += 1
        uv, z = uv_a[keep], z[keep]
        size = (a.image.shape[1], a.image.shape[0])
        net = model.predict_inv_depth(a.image, camera=cam).inv_depth_per_m
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_net = sample_map(net, uv, size)
            z_net = np.where(inv_net > 0, 1.0 / inv_net, np.nan)
            if oracle:
                inv_or = sample_map(oracle_inv_depth(seq, i, net.shape, num_disparities), uv, size)
                z_or = np.where(inv_or > 0, 1.0 / inv_or, np.nan)
            else:
                z_or = np.full(len(z), np.nan)
        # disparity_at: median of the valid (> 0) values in a 5x5 window; works on any such map
        z_d0 = disparity_at(a.depth_m, uv) if a.depth_m is not None else np.full(len(z), np.nan)
        for k, v in (("frame", np.full(len(z), i)), ("u", uv[:, 0]), ("v", uv[:, 1]), ("z_tri", z),
                     ("z_net", z_net), ("z_oracle", z_or), ("z_depth0", z_d0)):
            cols[k].append(v)
    out = {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in cols.items()}
    out["pairs"] = pairs
    return out


def slam_landmark_fractions(seq, model: DepthModel, preset: str) -> dict:
    """Where the SLAM's own scale landmarks fall: :func:`slam_landmarks.scale_landmark_depths`
    binned like the corners (fractions of all; ``<2`` and ``>60`` hold the rest)."""
    run = scale_landmark_depths(seq, model, preset)
    z = run.pop("depths_m")
    idx = bin_index(z)
    n = max(z.size, 1)
    fraction = {label: float(np.sum(idx == k)) / n for k, label in enumerate(BIN_LABELS)}
    fraction["<2"] = float(np.sum(z < RANGE_BINS_M[0][0])) / n
    fraction[">60"] = float(np.sum(z > RANGE_BINS_M[-1][1])) / n
    return {**run, "landmarks": int(z.size), "median_depth_m": float(np.median(z)) if z.size else None,
            "fraction": fraction}


def evaluate_sequence(seq_dir: str | Path, gt: str | Path, model: DepthModel, stride: int = 3, gap: int = 3,
                      min_parallax_deg: float = 1.0, num_disparities: int = 192, oracle: bool = True,
                      slam: bool = False, slam_preset_name: str | None = None) -> dict:
    """All of the module docstring for one sequence: JSON-ready dict with ``network`` and
    ``oracle`` (:func:`per_bin`), optional ``slam`` (:func:`slam_landmark_fractions`), counts, timing."""
    t0 = time.perf_counter()
    seq = open_sequence(seq_dir, poses_file=gt)
    s = landmark_samples(seq, model, stride, gap, min_parallax_deg, num_disparities, oracle)
    res = {"name": seq.name, "seq_dir": str(seq_dir), "gt": str(gt), "frames": len(seq), "pairs": s["pairs"],
           "corners": int(s["z_tri"].size), "network": per_bin(s["z_tri"], s["z_net"]),
           "oracle": per_bin(s["z_tri"], s["z_oracle"]) if oracle else None,
           "depth_0": per_bin(s["z_tri"], s["z_depth0"]) if np.isfinite(s["z_depth0"]).any() else None}
    per_frame = []
    for f in np.unique(s["frame"]).astype(int):
        m = s["frame"] == f
        per_frame.append({"frame": int(f), "n": int(m.sum()),
                          "network_median": ratio_stats(s["z_net"][m] / s["z_tri"][m])["median"]})
    res["per_frame"] = per_frame
    res["eval_s"] = time.perf_counter() - t0
    if slam:
        t1 = time.perf_counter()
        res["slam"] = slam_landmark_fractions(seq, model, slam_preset_name or preset_for(seq_dir))
        res["slam"]["wall_s"] = time.perf_counter() - t1
    return res


def summary(result: dict) -> dict:
    """Per sequence: ``worst_abs_log_ratio`` — the largest ``|log median(z_net/z_tri)|`` over
    :data:`SUMMARY_BINS` with ≥ :data:`SUMMARY_MIN_CORNERS` corners (None if none has) — its
    ``worst_bin``, the ``abs_log_ratio`` of each such bin, and, when the SLAM's landmark
    fractions were measured, ``vo_weighted_abs_log_ratio`` (Σ fraction·|log ratio| over the bins
    2–60 m with ≥ :data:`SUMMARY_MIN_CORNERS` corners, fractions renormalized over them).

    Args:
        result: what :func:`evaluate` returns (``{"sequences": {name: …}}``), or one sequence's
            :func:`evaluate_sequence` dict.
    """
    seqs = result["sequences"] if "sequences" in result else {result["name"]: result}
    out = {}
    for name, res in seqs.items():
        per = {b: abs(float(np.log(res["network"][b]["median"]))) for b in SUMMARY_BINS
               if res["network"][b]["n"] >= SUMMARY_MIN_CORNERS and res["network"][b]["median"]}
        worst = max(per, key=per.get) if per else None
        row = {"worst_abs_log_ratio": per[worst] if worst else None, "worst_bin": worst, "abs_log_ratio": per}
        if res.get("slam"):
            frac = res["slam"]["fraction"]
            used = [b for b in BIN_LABELS if res["network"][b]["n"] >= SUMMARY_MIN_CORNERS
                    and res["network"][b]["median"] and frac[b] > 0]
            total = sum(frac[b] for b in used)
            row["vo_weighted_abs_log_ratio"] = (
                sum(frac[b] * abs(float(np.log(res["network"][b]["median"]))) for b in used) / total
                if total > 0 else None)
        out[name] = row
    return out


def evaluate(seqs: list[tuple[str, str]], model_path: str | Path | None = None, name: str = "", **kw) -> dict:
    """Score one model on ``[(seq_dir, gt_poses), …]``; ``kw`` go to :func:`evaluate_sequence`.
    Returns ``{"name", "model", "params", "sequences": {seq name: …}, "summary"}``."""
    path = Path(model_path) if model_path is not None else DEFAULT_MODEL_PATH
    model = DepthModel.load(path, threads=1)
    shown = os.path.relpath(path) if path.resolve().is_relative_to(Path.cwd()) else str(path)
    out = {"name": name, "model": {"path": shown, "model_id": model.contract.model_id,
                                   "weights_precision": model.contract.weights_precision},
           "params": {"bins_m": RANGE_BINS_M, **kw}, "sequences": {}}
    for seq_dir, gt in seqs:
        res = evaluate_sequence(seq_dir, gt, model, **kw)
        key, k = res["name"], 2
        while key in out["sequences"]:
            key, k = f"{res['name']}#{k}", k + 1
        out["sequences"][key] = res
    out["summary"] = summary(out)
    return out


def _cell(stats: dict) -> str:
    return "–" if not stats["n"] else f"×{stats['median']:.3f} ({stats['n']})"


def _iqr(stats: dict) -> str:
    return "–" if not stats["n"] else f"{stats['p25']:.2f}–{stats['p75']:.2f}"


def markdown(result: dict, command: str, machine: str) -> str:
    """The per-sequence tables (rows network / oracle, cells ``×median ratio (n)``)."""
    m = result["model"]
    cols = [*BIN_LABELS, "all"]
    title = "# Landmark depth: network vs GT-triangulated corners"
    title += f" — {result['name']}" if result["name"] else ""
    lines = [title, "", f"Command: `{command}`  ", f"Machine: {machine}  ",
             f"Model: `{m['path']}` (`{m['model_id']}`, {m['weights_precision']})  ",
             f"Parameters: {', '.join(f'{k}={v}' for k, v in result['params'].items() if k != 'bins_m')}", "",
             ("Cells: median of z/z_tri (corners); IQR rows: its 25th–75th percentile. z_tri: corners "
              "tracked over `gap` frames, triangulated with the ground-truth motion (bench/landmark_depth.py)."), ""]
    for name, res in result["sequences"].items():
        summ = result["summary"][name]
        slam_s = f", SLAM run {res['slam']['wall_s']:.0f} s" if res.get("slam") else ""
        lines += [f"## {name} ({res['pairs']} frame pairs, {res['corners']} corners; {res['eval_s']:.0f} s{slam_s})",
                  "", f"| {name} | " + " | ".join(f"{c} m" if c != "all" else c for c in cols) + " |",
                  "| --- |" + " --- |" * len(cols),
                  "| network | " + " | ".join(_cell(res["network"][c]) for c in cols) + " |",
                  "| network IQR | " + " | ".join(_iqr(res["network"][c]) for c in cols) + " |"]
        if res["oracle"]:
            lines += ["| oracle (SGBM on the net grid) | " + " | ".join(_cell(res["oracle"][c]) for c in cols) + " |",
                      "| oracle IQR | " + " | ".join(_iqr(res["oracle"][c]) for c in cols) + " |"]
        if res.get("depth_0"):
            lines.append("| check: depth_0 (LiDAR / rendered) | " + " | ".join(_cell(res["depth_0"][c]) for c in cols)
                         + " |")
        if res.get("slam"):
            fr = res["slam"]["fraction"]
            lines.append("| SLAM scale landmarks % | " + " | ".join(f"{100 * fr[c]:.0f} %" for c in BIN_LABELS)
                         + f" | {res['slam']['landmarks']} (<2 m {100 * fr['<2']:.0f} %, >60 m "
                         f"{100 * fr['>60']:.0f} %) |")
        worst = summ["worst_abs_log_ratio"]
        lines += ["", f"worst |log ratio| (bins 5–60 m, ≥ {SUMMARY_MIN_CORNERS} corners): "
                  + (f"**{worst:.3f}** ({summ['worst_bin']} m)" if worst is not None else "n/a")
                  + (f"; VO-landmark-weighted |log ratio|: {summ['vo_weighted_abs_log_ratio']:.3f}"
                     if summ.get("vo_weighted_abs_log_ratio") is not None else ""), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", action="append", required=True, metavar="SEQ_DIR", help="KITTI-layout folder (repeat)")
    p.add_argument("--gt", action="append", required=True, metavar="POSES.txt",
                   help="its ground-truth T_world_cam0 poses (one per --seq, same order)")
    p.add_argument("--model", default=None, help=f"ONNX depth model (default: {DEFAULT_MODEL_PATH.name}, shipped)")
    p.add_argument("--name", default="", help="label of this run (e.g. the model's)")
    p.add_argument("--stride", type=int, default=3)
    p.add_argument("--gap", type=int, default=3)
    p.add_argument("--min-parallax-deg", type=float, default=1.0)
    p.add_argument("--num-disparities", type=int, default=192,
                   help="SGBM range of the oracle (multiple of 16; 192 px reaches 2 m on KITTI)")
    p.add_argument("--no-oracle", action="store_true", help="skip the SGBM oracle (no right images needed)")
    p.add_argument("--slam", action="store_true", help="also histogram the SLAM's own scale-landmark depths")
    p.add_argument("--slam-preset", default=None, choices=("kitti", "euroc", "tum", "synth"),
                   help="VO preset of --slam (default: as metricslam run picks it)")
    p.add_argument("--out", metavar="PREFIX", help="write PREFIX.json and PREFIX.md")
    args = p.parse_args(argv)
    if len(args.seq) != len(args.gt):
        p.error(f"give one --gt per --seq ({len(args.seq)} --seq, {len(args.gt)} --gt)")
    cv2.setNumThreads(1)
    command = command_line("bench.landmark_depth", argv)
    result = evaluate(list(zip(args.seq, args.gt)), args.model, args.name, stride=args.stride, gap=args.gap,
                      min_parallax_deg=args.min_parallax_deg, num_disparities=args.num_disparities,
                      oracle=not args.no_oracle, slam=args.slam, slam_preset_name=args.slam_preset)
    publish(args.out, result, command, markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
