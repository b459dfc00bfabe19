"""Upper bound of the learned-scale pipeline: the same SLAM with a *stereo* depth source.

Separates what the global graph and the warp can do from what the depth network delivers:
the depth source is replaced by OpenCV SGBM on the rectified stereo pair (metric inverse depth,
pooled to the network's 32x64 grid by the median of valid disparities per cell). Everything
else — VO, Sim(3) graph, per-keyframe scale factors, loops, warp — is ``metricslam run
--deterministic``'s default (``--live`` for the threaded default). This is NOT the method (it uses
the right camera); it is the ceiling the network can approach — as far as the stereo pair is right.

Three depth sources per sequence (``--variants``):

* ``legacy`` — the first version: SGBM with 64 disparities (nothing nearer than ~6 m), no
  left-right check, cells without valid disparities set to 0 (bilinear sampling then blends the
  0 into neighbouring landmarks' inverse depth, i.e. pushes them away).
* ``stereo`` — full-resolution SGBM with 128 disparities and a left-right consistency check
  (:func:`metricslam.stereo.block_matching_pair`, the matcher of the training labels);
  cells with fewer than 10 % valid pixels are NaN (samples touching them are dropped).
* ``stereo_selfcal`` — ``stereo`` plus a disparity offset δ (px) added to every disparity,
  self-calibrated WITHOUT ground truth from a first, scale-free pass of the same VO: at each
  keyframe's landmarks the measured disparity must be affine in the VO inverse depth,
  ``log ξ_j − log(d_j + δ)`` must be the same for all landmarks of a keyframe (its scale); δ
  minimizes their pooled robust spread (see :func:`fit_disparity_offset`).
  A rectified pair whose calibration is off by a horizontal principal-point shift has such a
  constant disparity offset, which biases metric depth the more the farther the scene
  (KITTI 01: see ``bench/results/scale_upper_bound.md``).
* ``rendered`` — rendered sequences only (``metricslam synth``, ``depth_0``): the exact inverse
  depth, median per cell of the 32x64 grid — a depth network without error at the network's
  resolution. What the graph, the warp and the VO can reach when the depth is right.

Example::

    .venv/bin/python -m bench.scale_upper_bound --seq kitti06=/work/shared/data/kitti_odometry/sequences/06:/work/shared/data/kitti_odometry/poses/06.txt \\
        --out bench/results/scale_upper_bound
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from bench.gt_corners import intrinsics, triangulate_gt
from bench.machine import command_line, describe, write_results
from metricslam.datasets.kitti import KittiOdometry
from metricslam.slam.session_builder import build_session
from metricslam.slam.system_config import SystemConfig
from metricslam.stereo import block_matching_pair
from metricslam.trajectory.io import write_kitti_poses

VARIANTS = ("legacy", "stereo", "stereo_selfcal", "rendered")


def pool_cells(disp_px: np.ndarray, grid_hw: tuple[int, int], min_valid: int, empty: float) -> np.ndarray:
    """(h, w) median of valid (> 0) disparities per cell; ``empty`` where fewer than ``min_valid``."""
    h, w = grid_hw
    H, W = disp_px.shape
    out = np.full((h, w), empty, np.float32)
    for i in range(h):
        for j in range(w):
            cell = disp_px[i * H // h:(i + 1) * H // h, j * W // w:(j + 1) * W // w]
            valid = cell[cell > 0]
            if valid.size >= min_valid:
                out[i, j] = np.median(valid)
    return out


class ReferenceDepthSource:
    """``DepthSource`` from a reference instead of the network: SGBM on the stereo pair, or the
    rendered depth (right images and depths registered by the left image's hash).

    Args:
        baseline_m: stereo baseline (m).
        variant: ``"legacy"``, ``"stereo"`` or ``"rendered"`` (module docstring);
            ``stereo_selfcal`` is ``"stereo"`` with ``disparity_offset_px``.
        disparity_offset_px: δ added to every valid disparity (px) before converting to 1/m.
        grid_hw: output grid (the network's).
    """

    def __init__(self, baseline_m: float, variant: str = "stereo", disparity_offset_px: float = 0.0,
                 grid_hw: tuple[int, int] = (32, 64)) -> None:
        self.baseline_m = baseline_m
        self.variant = variant
        self.disparity_offset_px = float(disparity_offset_px)
        self.grid_hw = grid_hw
        self.right: dict[str, np.ndarray] = {}
        self.depth_m: dict[str, np.ndarray] = {}

    @staticmethod
    def _key(image: np.ndarray) -> str:
        return hashlib.blake2b(np.ascontiguousarray(image).tobytes(), digest_size=16).hexdigest()

    def register(self, left: np.ndarray, right: np.ndarray, depth_m: np.ndarray | None = None) -> None:
        """Remember what ``left``'s depth map is made from: its right image, or for ``rendered``
        its true depth (H, W) m. Kept for the whole run (``self_calibrate`` revisits keyframes)."""
        if self.variant != "rendered":
            self.right[self._key(left)] = right
        elif depth_m is None:
            raise ValueError("the 'rendered' variant needs a sequence with depth_0 (metricslam synth)")
        else:
            self.depth_m[self._key(left)] = depth_m

    def disparity(self, image: np.ndarray) -> np.ndarray:
        """Full-resolution disparity (H, W) px of a registered left image, 0 = invalid, no offset."""
        right = self.right[self._key(image)]
        if self.variant == "legacy":
            sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=64, blockSize=7, P1=8 * 49,
                                         P2=32 * 49, uniquenessRatio=10)
            disp = sgbm.compute(image, right).astype(np.float32) / 16.0
            return np.where(disp >= 1.0, disp, 0.0).astype(np.float32)
        return block_matching_pair(image, right)[0]

    def inv_depth_map(self, image: np.ndarray, camera) -> np.ndarray:
        h, w = self.grid_hw
        if self.variant == "rendered":
            depth_m = self.depth_m[self._key(image)]
            inv = np.where(depth_m > 0, 1.0 / np.maximum(depth_m, 1e-6), 0.0).astype(np.float32)
            n_px = (inv.shape[0] // h) * (inv.shape[1] // w)
            return pool_cells(inv, self.grid_hw, min_valid=max(10, n_px // 10), empty=np.nan)
        disp = self.disparity(image)
        if self.variant == "legacy":
            cells = pool_cells(disp, self.grid_hw, min_valid=11, empty=0.0)
        else:
            n_px = (disp.shape[0] // h) * (disp.shape[1] // w)
            cells = pool_cells(disp, self.grid_hw, min_valid=max(10, n_px // 10), empty=np.nan)
            cells = cells + self.disparity_offset_px
        return cells / (camera.fx_px * self.baseline_m)


def disparity_at(disp_px: np.ndarray, uv_px: np.ndarray, radius: int = 2, min_valid: int = 3) -> np.ndarray:
    """(N,) median valid disparity in a (2r+1)² window around each pixel, NaN if too few."""
    out = np.full(len(uv_px), np.nan)
    H, W = disp_px.shape
    for k, (u, v) in enumerate(np.asarray(uv_px, float)):
        ui, vi = int(np.rint(u)), int(np.rint(v))
        win = disp_px[max(vi - radius, 0):min(vi + radius + 1, H), max(ui - radius, 0):min(ui + radius + 1, W)]
        win = win[win > 0]
        if win.size >= min_valid:
            out[k] = np.median(win)
    return out


def fit_disparity_offset(per_keyframe: list[tuple[np.ndarray, np.ndarray]], min_landmarks: int = 8,
                         search_px: tuple[float, float] = (-2.0, 4.0), step_px: float = 0.01) -> dict:
    """Shared disparity offset δ (px) that makes each keyframe's landmark scales agree (no GT).

    With the right δ every landmark ``j`` of keyframe ``i`` measures the same scale,
    ``log ξ_j − log(d_j + δ) = const_i``; a wrong δ spreads them depth-dependently (far landmarks,
    small ``d``, move most). δ minimizes the pooled median absolute deviation of these per-keyframe
    centred log-ratios (grid search). Scale-free: only the VO's relative structure and the pair.

    Args:
        per_keyframe: per keyframe ``(ξ (M,) VO inverse depth, d (M,) measured disparity px)``.

    Returns:
        ``{"offset_px": δ, "mad_log_at_zero", "mad_log_at_offset", "keyframes", "landmarks"}``.
    """
    blocks = []
    for xi, d in per_keyframe:
        ok = np.isfinite(xi) & np.isfinite(d) & (xi > 0) & (d > 0)
        if ok.sum() >= min_landmarks:
            blocks.append((np.log(xi[ok]), d[ok]))
    if not blocks:
        raise ValueError("no keyframe has enough landmarks with stereo disparity")

    def spread(delta: float) -> float:
        res = []
        for log_xi, d in blocks:
            r = log_xi - np.log(np.maximum(d + delta, 1e-3))
            res.append(r - np.median(r))
        return float(np.median(np.abs(np.concatenate(res))))

    grid = np.arange(search_px[0], search_px[1] + step_px / 2, step_px)
    costs = np.array([spread(float(g)) for g in grid])
    best = float(grid[int(np.argmin(costs))])
    return {"offset_px": best, "mad_log_at_zero": spread(0.0), "mad_log_at_offset": float(costs.min()),
            "keyframes": len(blocks), "landmarks": int(sum(len(d) for _, d in blocks))}


def stereo_check(seq: KittiOdometry, gap: int = 2, stride: int = 3) -> dict:
    """EVALUATION ONLY (uses ground truth): is the stereo pair's disparity consistent with GT motion?

    Corners of frame k are tracked (forward-backward LK) to frame k+gap and triangulated with the
    GT relative pose (metric, independent of the VO); their disparity ``f·B/Z`` is compared with
    the LR-checked SGBM disparity (:func:`metricslam.stereo.block_matching_pair`, the matcher of
    the depth network's training labels; 5x5 median) at the corner. ``seq`` must carry its
    ground-truth poses. A constant difference over depth is a
    rectification/calibration offset of the pair. Also: the fraction of corners whose left-to-right
    LK match has a negative disparity (impossible for a correctly rectified pair).
    """
    cam = seq.camera
    K = intrinsics(cam)
    fb = cam.fx_px * seq.baseline_m
    T_world_cam = seq.T_world_cam_gt
    if T_world_cam is None:
        raise ValueError(f"{seq.name}: stereo_check needs the ground-truth poses")

    lk = {"winSize": (21, 21), "maxLevel": 3}
    z_gt, d_gt, d_sgbm, d_lk = [], [], [], []
    for k in range(0, len(seq) - gap, stride):
        a, b = seq[k], seq[k + gap]
        p0 = cv2.goodFeaturesToTrack(a.image, 800, 0.01, 8)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(a.image, b.image, p0, None, **lk)
        pb, st2, _ = cv2.calcOpticalFlowPyrLK(b.image, a.image, p1, None, **lk)
        ok = (st[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm(pb - p0, axis=2)[:, 0] < 0.5)
        x0, x1 = p0[ok, 0].astype(float), p1[ok, 0].astype(float)
        T_b_a = np.linalg.inv(T_world_cam[k + gap]) @ T_world_cam[k]
        good, z = triangulate_gt(x0, x1, K, T_b_a, depth_range_m=(3.0, 80.0), min_parallax_deg=2.0)
        d = disparity_at(block_matching_pair(a.image, a.image_right)[0], x0[good])
        z_gt += list(z[good])
        d_gt += list(fb / z[good])
        d_sgbm += list(d)
        q1, st, _ = cv2.calcOpticalFlowPyrLK(a.image, a.image_right, p0, None, winSize=(21, 21), maxLevel=4)
        qb, st2, _ = cv2.calcOpticalFlowPyrLK(a.image_right, a.image, q1, None, winSize=(21, 21), maxLevel=4)
        ok = (st[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm(qb - p0, axis=2)[:, 0] < 0.3)
        d_lk += list((p0 - q1)[ok, 0, 0])
    z_gt, d_gt, d_sgbm = np.array(z_gt), np.array(d_gt), np.array(d_sgbm)
    ok = np.isfinite(d_sgbm)
    bins = {}
    for lo, hi in ((3, 12), (12, 20), (20, 40), (40, 80)):
        m = ok & (z_gt >= lo) & (z_gt < hi)
        if m.sum() >= 5:
            bins[f"{lo}-{hi} m"] = {"n": int(m.sum()), "d_sgbm_minus_d_gt_px": float(np.median(d_sgbm[m] - d_gt[m])),
                                    "depth_ratio_sgbm_over_gt": float(np.median(d_gt[m] / d_sgbm[m]))}
    d_lk = np.array(d_lk)
    return {"n": int(ok.sum()), "d_sgbm_minus_d_gt_px": float(np.median(d_sgbm[ok] - d_gt[ok])),
            "depth_ratio_sgbm_over_gt": float(np.median(d_gt[ok] / d_sgbm[ok])), "bins": bins,
            "lk_negative_disparity_fraction": float(np.mean(d_lk < 0))}


def system_config(live: bool, use_scale: bool = True) -> SystemConfig:
    """The KITTI preset and graph defaults, as ``metricslam run [--deterministic]`` builds them
    (the graph's live depth queue: this bench never loads the machine enough to drop)."""
    return SystemConfig(vo={"preset": "kitti"}, depth={"use_scale": use_scale}, deterministic=not live)


def self_calibrate(seq: KittiOdometry, live: bool) -> dict:
    """Pass 1: the same VO without scale factors; fit δ at its keyframes' landmarks (no GT)."""
    pipe = build_session(seq.camera, system_config(live, use_scale=False))
    keyframes = []
    forward = pipe.backend.on_keyframe_marginalized

    def record(kf):
        keyframes.append(kf)
        return forward(kf)

    pipe.backend.on_keyframe_marginalized = record
    src = ReferenceDepthSource(seq.baseline_m)
    for i in range(len(seq)):
        f = seq[i]
        src.register(f.image, f.image_right)
        pipe.process(f)
    pipe.close()
    per_kf = []
    for kf in keyframes:
        if len(kf.landmarks_inv_depth) == 0:
            continue
        d = disparity_at(src.disparity(kf.image), kf.landmarks_uv_px)
        per_kf.append((np.asarray(kf.landmarks_inv_depth, float), d))
    return fit_disparity_offset(per_kf)


def run_one(seq: KittiOdometry, src: ReferenceDepthSource, live: bool) -> tuple[np.ndarray, dict, float]:
    pipe = build_session(seq.camera, system_config(live), depth_source=src)
    t0 = time.perf_counter()
    for i in range(len(seq)):
        f = seq[i]
        src.register(f.image, f.image_right, f.depth_m)
        pipe.process(f)
    pipe.close()
    wall = time.perf_counter() - t0
    return np.array([e.T_world_cam for e in pipe.trajectory()]), pipe.stats().get("backend", {}), wall


def evaluate(est_path: Path, gt: str) -> dict:
    out_json = est_path.with_suffix(".eval.json")
    subprocess.run([sys.executable, "-m", "metricslam_cli.main", "eval", "--gt", gt, "--est", str(est_path),
                    "--json", str(out_json)], check=True, capture_output=True)
    return json.loads(out_json.read_text())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", action="append", required=True, metavar="NAME=SEQ_DIR:GT.txt")
    p.add_argument("--variants", default=",".join(VARIANTS), help=f"comma list of {VARIANTS}")
    p.add_argument("--live", action="store_true",
                   help="threaded back end and BA (metricslam run's live default; depth requests "
                        "may be dropped, results vary run to run)")
    p.add_argument("--out", help="write OUT.md and OUT.json")
    args = p.parse_args(argv)
    variants = [v for v in args.variants.split(",") if v]
    if bad := set(variants) - set(VARIANTS):
        p.error(f"unknown variants {sorted(bad)}; choose from {VARIANTS}")
    rows, checks = [], {}
    work = Path(tempfile.mkdtemp(prefix="scale_bound_"))
    for spec in args.seq:
        name, rest = spec.split("=", 1)
        seq_dir, gt = rest.rsplit(":", 1)
        seq = KittiOdometry(seq_dir, gt)
        calib = None
        checks[name] = stereo_check(seq)
        print(json.dumps({"name": name, "stereo_check": {k: v for k, v in checks[name].items() if k != "bins"}}),
              flush=True)
        for variant in variants:
            offset = 0.0
            if variant == "stereo_selfcal":
                calib = calib or self_calibrate(seq, args.live)
                offset = calib["offset_px"]
            src = ReferenceDepthSource(seq.baseline_m, "stereo" if variant == "stereo_selfcal" else variant, offset)
            traj, backend, wall = run_one(seq, src, args.live)
            est = work / f"{name}_{variant}.txt"
            write_kitti_poses(est, traj)
            m = evaluate(est, gt)
            rows.append({"name": name, "variant": variant, "disparity_offset_px": offset,
                         "selfcal": calib if variant == "stereo_selfcal" else None, "metrics": m,
                         "backend": backend, "fps_incl_sgbm": len(seq) / wall})
            print(json.dumps({"name": name, "variant": variant, "offset_px": round(offset, 3),
                              "scale_error_pct": m["scale_error_pct"], "ate_rmse_m": m["ate_rmse_m"],
                              "t_rel_pct": m["t_rel_pct"]}), flush=True)
    if args.out:
        machine = describe()
        lines = ["# Upper bound: the same SLAM with stereo (SGBM) or rendered depth instead of the network", "",
                 f"Command: `{command_line('bench.scale_upper_bound', argv)}`  ", f"Machine: {machine}  ",
                 f"Mode: {'live (threaded)' if args.live else 'deterministic (inline graph, BA in foreground)'}",
                 "", "| run | depth source | δ px | path m | scale err % | ATE SE(3) m | ATE % path | ATE Sim(3) m | t_rel % |",
                 "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in rows:
            m = r["metrics"]
            off = (f"{r['disparity_offset_px']:+.2f} (MAD log {r['selfcal']['mad_log_at_zero']:.3f} -> "
                   f"{r['selfcal']['mad_log_at_offset']:.3f})" if r["selfcal"] else "0")
            lines.append(f"| {r['name']} | {r['variant']} | {off} | {m['path_length_m']:.0f} | "
                         f"{m['scale_error_pct']:.2f} | {m['ate_rmse_m']:.2f} | "
                         f"{100 * m['ate_rmse_m'] / m['path_length_m']:.2f} | {m['ate_rmse_sim3_m']:.2f} | "
                         f"{m['t_rel_pct']:.2f} |")
        lines += ["", ("Stereo pair vs ground-truth motion (evaluation only, `stereo_check`: corners "
                       "triangulated with GT poses 2 frames apart, vs LR-checked SGBM at the corner):"), "",
                  ("| run | corners | median d_SGBM − d_GT px | median Z_SGBM / Z_GT | per depth bin (Δd px) | "
                   "LK left→right d < 0 |"), "| --- | --- | --- | --- | --- | --- |"]
        for name, c in checks.items():
            per_bin = ", ".join(f"{k}: {v['d_sgbm_minus_d_gt_px']:+.2f} (n {v['n']})" for k, v in c["bins"].items())
            lines.append(f"| {name} | {c['n']} | {c['d_sgbm_minus_d_gt_px']:+.2f} | {c['depth_ratio_sgbm_over_gt']:.3f} | "
                         f"{per_bin} | {100 * c['lk_negative_disparity_fraction']:.1f} % |")
        write_results(args.out, {"rows": rows, "stereo_check": checks, "machine": machine,
                                 "command": command_line("bench.scale_upper_bound", argv), "live": bool(args.live)}, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
