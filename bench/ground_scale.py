"""Ground-plane scale (issue #33): each scale-source setting on real drives, scored against truth.

For every ``--seq`` (a KITTI-layout folder with its ``--poses`` file) and every source setting
(``[learned]``, ``[ground]``, ``[learned, ground]``) it runs the system of
``metricslam run SEQ --deterministic --scale-sources … --mount-height …`` in-process (the one
session builder, the preset ``run`` picks) and reports:

* trajectory: scale error, ATE (SE(3)) in m and % of the path, t_rel, frames/s;
* per keyframe, from the back end's events (``GroundScaleMeasured``, ``ScaleMeasured``): the road
  height in metres, ``h_vo · |t_true| / step_vo`` (the VO's keyframe step made metric by the true
  motion between the same two frames; no ground truth reaches the estimate), against the
  mounting height; the share of keyframes with a ground factor; the learned and the ground scale
  measurement per keyframe over the true one (``|t_true| / step_vo``, m per VO unit);
* the estimator alone: ``estimate_ground_height`` between frames ``gap`` apart with the TRUE
  relative pose (metres): its height error without any VO error.

Parameters are chosen on rendered streets and ONE drive (``--tuned-on``); the others are
reported as held out. Example::

    .venv/bin/python -m bench.ground_scale \\
        --seq ../shared/data/kitti_raw_stereo/sequences/2011_09_26_drive_0013 \\
        --poses ../shared/data/kitti_raw_stereo/poses/2011_09_26_drive_0013.txt \\
        --seq ../shared/data/kitti_odometry/sequences/06 --poses ../shared/data/kitti_odometry/poses/06.txt \\
        --tuned-on 2011_09_26_drive_0013 --out bench/results/ground_scale
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from bench.machine import command_line, publish
from metricslam.datasets import open_sequence
from metricslam.evaluation.evaluator import evaluate_poses
from metricslam.slam.events import GroundScaleMeasured, ScaleMeasured
from metricslam.slam.graph.scale_factor import robust_log_scale
from metricslam.slam.ground.height import RoadHeightEstimator
from metricslam.slam.session_builder import build_session, preset_for
from metricslam.slam.system_config import SystemConfig
from metricslam.trajectory.io import read_kitti_poses

SETTINGS = (("learned",), ("ground",), ("learned", "ground"))


def _pct(x: float) -> float:
    return round(100.0 * float(x), 2)


def run_setting(seq_dir: str, T_world_cam_gt: np.ndarray, sources: tuple[str, ...], h_mount_m: float) -> dict:
    """One deterministic run; trajectory metrics and per-keyframe measurements against truth."""
    seq = open_sequence(seq_dir)
    config = SystemConfig(deterministic=True, graph={"depth_queue_size": 256},
                          scale={"sources": list(sources), "mount_height_m": h_mount_m})
    pipe = build_session(seq.camera, config, default_preset=preset_for(seq_dir))
    ground: list[GroundScaleMeasured] = []
    learned: dict[int, float] = {}

    def on_event(ev: object) -> None:
        if isinstance(ev, GroundScaleMeasured):
            ground.append(ev)
        elif isinstance(ev, ScaleMeasured) and ev.scales.size:
            learned[ev.frame_index] = float(np.exp(robust_log_scale(ev.scales, 0.15, 1.345)[0]))

    pipe.backend.events.subscribe(on_event)
    t0 = time.perf_counter()
    try:
        for i in range(len(seq)):
            pipe.process(seq[i])
    finally:
        pipe.close()
    wall_s = time.perf_counter() - t0
    est = np.array([e.T_world_cam for e in pipe.trajectory()])
    ev = evaluate_poses(T_world_cam_gt[: len(est)], est, name=Path(seq_dir).name).result
    stats = pipe.stats()
    out = {"scale_error_pct": round(ev.scale_error_pct, 2), "scale_ratio": round(ev.scale_ratio, 4),
           "ate_rmse_m": round(ev.ate_rmse_m, 3), "ate_pct_of_path": _pct(ev.ate_rmse_m / ev.path_length_m),
           "t_rel_pct": None if ev.t_rel_pct is None else round(ev.t_rel_pct, 2),
           "path_length_m": round(ev.path_length_m, 1), "fps": round(len(seq) / wall_s, 1),
           "keyframes": int(stats["keyframes"])}
    per_kf = []
    for g in ground:
        if g.prev_frame_index < 0 or not np.isfinite(g.step_vo):
            continue
        true_m = float(np.linalg.norm(T_world_cam_gt[g.frame_index][:3, 3] - T_world_cam_gt[g.prev_frame_index][:3, 3]))
        s_true = true_m / g.step_vo  # metres per keyframe VO unit
        per_kf.append({"frame": g.frame_index, "accepted": bool(g.accepted), "reason": g.reason,
                       "height_m": g.height_vo * s_true if np.isfinite(g.height_vo) else None,
                       "ground_over_true": g.scale / s_true if g.accepted else None,
                       "learned_over_true": learned[g.frame_index] / s_true if g.frame_index in learned else None})
    if ground:
        h = np.array([k["height_m"] for k in per_kf if k["accepted"]], dtype=float)
        h_all = np.array([k["height_m"] for k in per_kf if k["height_m"] is not None], dtype=float)
        health = stats["backend"].get("scale_health", {})
        out["ground"] = {
            "keyframes_with_factor_pct": _pct(sum(g.accepted for g in ground) / max(len(ground), 1)),
            "height_median_abs_err_pct": _pct(np.median(np.abs(h / h_mount_m - 1))) if h.size else None,
            "height_median_m": round(float(np.median(h)), 3) if h.size else None,
            "height_median_abs_err_pct_all_estimates": _pct(np.median(np.abs(h_all / h_mount_m - 1))) if h_all.size else None,
            "rejected": stats["backend"].get("ground_rejected_reasons", {}),
            "health_warnings_issued": health.get("warnings_issued"), "health_warning_at_end": health.get("warning"),
            "health_disagreement_log_median": health.get("disagreement_log_median")}
        out["per_keyframe"] = per_kf
    for name in ("learned_over_true", "ground_over_true"):
        vals = [k[name] for k in per_kf if k[name] is not None]
        if vals:
            out.setdefault("ground", {})[f"{name}_median"] = round(float(np.median(vals)), 4)
    return out


def estimator_alone(seq_dir: str, T_world_cam_gt: np.ndarray, h_mount_m: float, gap: int) -> dict:
    """``RoadHeightEstimator`` between frames ``gap`` apart with the TRUE relative pose (m)."""
    seq = open_sequence(seq_dir)
    est = RoadHeightEstimator()
    h, acc, ms = [], [], []
    for i in range(gap, len(seq), gap):
        a, b = seq[i - gap].image, seq[i].image
        T_prev_cur = np.linalg.inv(T_world_cam_gt[i - gap]) @ T_world_cam_gt[i]
        t0 = time.perf_counter()
        r = est.estimate(a, b, seq.camera.K, T_prev_cur)
        ms.append(1e3 * (time.perf_counter() - t0))
        h.append(r.height)
        acc.append(r.accepted)
    h, acc = np.array(h), np.array(acc)
    ok = h[acc]
    return {"pairs": len(h), "gap_frames": gap, "accepted_pct": _pct(acc.mean()),
            "height_median_m": round(float(np.median(ok)), 3) if ok.size else None,
            "median_abs_err_pct": _pct(np.median(np.abs(ok / h_mount_m - 1))) if ok.size else None,
            "mad_pct": _pct(np.median(np.abs(ok - np.median(ok))) / h_mount_m) if ok.size else None,
            "ms_mean": round(float(np.mean(ms)), 1)}


def evaluate(seqs: list[str], poses: list[str], h_mount_m: float, tuned_on: str, gap: int) -> dict:
    cv2.setNumThreads(1)
    result = {"mount_height_m": h_mount_m, "tuned_on": tuned_on, "sequences": {}}
    for seq_dir, pose_file in zip(seqs, poses):
        gt = read_kitti_poses(pose_file)
        name = Path(seq_dir).name
        entry = {"role": "tuning" if name == tuned_on else "held out",
                 "estimator_true_motion": estimator_alone(seq_dir, gt, h_mount_m, gap)}
        for sources in SETTINGS:
            entry[",".join(sources)] = run_setting(seq_dir, gt, sources, h_mount_m)
        result["sequences"][name] = entry
    return result


def markdown(result: dict, command: str, machine: str) -> str:
    lines = ["# Ground-plane scale (issue #33)", "",
             f"Camera {result['mount_height_m']} m above the road. Estimator parameters chosen on rendered "
             f"streets and `{result['tuned_on']}`; every other drive is held out. Frames/s mean something "
             "only on a quiet machine (the load average below says whether one was). The health "
             "warning's window was 5 keyframes in a first run of this bench (warnings on both drives, "
             "flapping); it is now 15, the network error's documented correlation length, with "
             "hysteresis — chosen from that documentation, but after seeing both drives. The height "
             "consistency gate (a height more than 25 % from the median of the last 10 accepted ones "
             "is refused: the car close ahead on 0013 frames 65–72) was added after seeing both "
             "drives' earlier results; its bound and window were chosen on 0013 alone, and 06 was "
             "only rerun.", "",
             "| drive | role | sources | scale err % | ATE m (% path) | t_rel % | keyframes w/ ground % | "
             "height median |err| % (median m) | frames/s |", "|---|---|---|---|---|---|---|---|---|"]
    for name, e in result["sequences"].items():
        for sources in SETTINGS:
            r = e[",".join(sources)]
            g = r.get("ground", {})
            lines.append(f"| {name} | {e['role']} | {','.join(sources)} | {r['scale_error_pct']} | "
                         f"{r['ate_rmse_m']} ({r['ate_pct_of_path']}) | {r['t_rel_pct']} | "
                         f"{g.get('keyframes_with_factor_pct', '—')} | {g.get('height_median_abs_err_pct', '—')} "
                         f"({g.get('height_median_m', '—')}) | {r['fps']} |")
    lines += ["", "Scale health with learned,ground (median log(learned / ground) per keyframe; warnings):", ""]
    for name, e in result["sequences"].items():
        g = e["learned,ground"].get("ground", {})
        d = g.get("health_disagreement_log_median")
        lines.append(f"* {name}: learned/ground median {'—' if d is None else f'{np.exp(d):.3f}'}, "
                     f"learned/true {g.get('learned_over_true_median')}, ground/true "
                     f"{g.get('ground_over_true_median')}; warnings {g.get('health_warnings_issued')}")
    lines += ["", "Estimator alone (true relative pose between frames `gap` apart):", "",
              "| drive | pairs | accepted % | median height m | median |err| % | MAD % | ms |",
              "|---|---|---|---|---|---|---|"]
    for name, e in result["sequences"].items():
        a = e["estimator_true_motion"]
        lines.append(f"| {name} | {a['pairs']} | {a['accepted_pct']} | {a['height_median_m']} | "
                     f"{a['median_abs_err_pct']} | {a['mad_pct']} | {a['ms_mean']} |")
    lines += ["", f"Command: `{command}`", "", f"Machine: {machine}", ""]
    return "\n".join(lines)


def plot(result: dict, path: str) -> None:
    """Per-keyframe learned and ground scale measurements over the true scale, per drive."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(result["sequences"])
    fig, axes = plt.subplots(len(names), 1, figsize=(9, 3.2 * len(names)), squeeze=False)
    for ax, name in zip(axes[:, 0], names):
        kfs = result["sequences"][name]["learned,ground"].get("per_keyframe", [])
        for key, label, style in (("learned_over_true", "learned (network)", "o-"),
                                  ("ground_over_true", "ground (road plane)", "s-")):
            pts = [(k["frame"], k[key]) for k in kfs if k[key] is not None]
            if pts:
                ax.plot(*zip(*pts), style, ms=3, label=label)
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_title(f"{name}: keyframe scale measurement / truth")
        ax.set_xlabel("frame")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", action="append", required=True, help="KITTI-layout folder (repeat)")
    p.add_argument("--poses", action="append", required=True, help="its KITTI pose file (repeat, same order)")
    p.add_argument("--mount-height", type=float, default=1.65, help="camera height above the road (m)")
    p.add_argument("--tuned-on", default="2011_09_26_drive_0013", help="the drive parameters were chosen on")
    p.add_argument("--gap", type=int, default=3, help="frames between pairs for the estimator-alone check")
    p.add_argument("--out", metavar="PREFIX", help="write PREFIX.json and PREFIX.md")
    p.add_argument("--plot", metavar="PNG", help="per-keyframe scale of each source vs truth (matplotlib)")
    args = p.parse_args(argv)
    if len(args.seq) != len(args.poses):
        p.error("give one --poses per --seq")
    result = evaluate(args.seq, args.poses, args.mount_height, args.tuned_on, args.gap)
    publish(args.out, result, command_line("bench.ground_scale", argv), markdown)
    if args.plot:
        plot(result, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
