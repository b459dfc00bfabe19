"""Local VO accuracy and speed: Sim(3)-aligned ATE (% of distance), KITTI r_rel, frames/s and
per-stage ms on real KITTI extracts and a synthetic sequence.

The VO runs alone (``SlamPipeline`` without a back end: no global graph, no learned scale), so
the Sim(3) alignment is the honest comparison for a monocular estimate. Images are decoded
before the clock starts (frames/s is the VO's, not the PNG decoder's; decode time is reported
separately). Ground truth is read only by the evaluator.

Example (the synthetic sequence is rendered first; seed and length as in the results)::

    .venv/bin/metricslam synth /tmp/synth_vo_600 --frames 600 --seed 7 --path loop
    .venv/bin/python -m bench.vo_accuracy \\
        --seq ../shared/data/kitti_odometry/sequences/06 \\
        --seq ../shared/data/kitti_odometry/sequences/01 \\
        --seq /tmp/synth_vo_600 --out bench/results/vo.md
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from bench.machine import command_line, describe
from metricslam.datasets import open_sequence
from metricslam.evaluation import evaluate_poses
from metricslam.slam.session_builder import build_session, preset_for
from metricslam.slam.system_config import SystemConfig


def run_sequence(path: Path, preset: str | None, background: bool, max_frames: int | None) -> dict:
    seq = open_sequence(path)
    if seq.T_world_cam_gt is None:
        raise SystemExit(f"{path}: no ground truth to evaluate against")
    n = len(seq) if max_frames is None else min(max_frames, len(seq))
    preset = preset or preset_for(path)
    t0 = time.perf_counter()
    frames = [seq[i] for i in range(n)]
    decode_s = time.perf_counter() - t0
    config = SystemConfig(vo={"preset": preset, "ba_in_background": background}, vo_only=True)
    pipe = build_session(seq.camera, config)
    t0, c0 = time.perf_counter(), time.process_time()
    for f in frames:
        pipe.process(f)
    process_s = time.perf_counter() - t0
    pipe.close()
    total_s = time.perf_counter() - t0
    cpu_s = time.process_time() - c0  # all threads of this process (tracking + BA worker)
    est = np.array([e.T_world_cam for e in pipe.trajectory()])
    ev = evaluate_poses(seq.T_world_cam_gt[:n], est, name=path.name).result
    st = pipe.stats()
    return {"sequence": str(path), "name": path.name, "preset": preset, "frames": n, "background_ba": background,
        "path_length_m": ev.path_length_m, "ate_sim3_m": ev.ate_rmse_sim3_m,
        "ate_sim3_pct_of_distance": 100.0 * ev.ate_rmse_sim3_m / ev.path_length_m,
        "r_rel_deg_per_100m": ev.r_rel_deg_per_100m, "t_rel_pct_unscaled": ev.t_rel_pct,
        "t_rel_lengths_m": ev.t_rel_lengths_m, "scale_ratio": ev.scale_ratio, "rpe_rot_rmse_deg": ev.rpe_rot_rmse_deg,
        "fps_process": n / process_s, "fps_including_flush": n / total_s,
        "cpu_ms_per_frame": 1e3 * cpu_s / n, "fps_cpu_bound": n / cpu_s, "decode_ms_per_frame": 1e3 * decode_s / n,
        "keyframes": st["keyframes"], "tracking_losses": st["tracking_losses"],
        "ms_per_frame": st["ms_per_frame"], "ms_per_call": st["ms_per_call"]}


def to_markdown(rows: list[dict], command: str, host: str, notes: list[str]) -> str:
    out = ["# Local VO accuracy and speed", "", f"Command: `{command}`", "", f"Machine: {host}", "",
           *[f"* {n}" for n in notes], *([""] if notes else []),
           "VO alone (no global graph, no learned scale); ATE after Sim(3) alignment, as % of the "
           "ground-truth path length; r_rel is the KITTI devkit rotational error (deg/100 m) over "
           "the segment lengths that fit (10..50 m for these short extracts). Frames/s excludes PNG "
           "decoding (listed separately).", "",
           "| sequence | BA | frames | path m | KFs | losses | ATE Sim3 m | ATE % dist | r_rel deg/100m | "
           "fps (wall) | CPU ms/frame | frontend ms | pose ms | keyframe ms | BA ms/solve | "
           "marg ms/KF | decode ms |", "|" + " --- |" * 17]
    for r in rows:
        pf, pc = r["ms_per_frame"], r["ms_per_call"]
        out.append(
            f"| {r['name']} | {'worker' if r['background_ba'] else 'inline'} | {r['frames']} | {r['path_length_m']:.1f} | {r['keyframes']} | "
            f"{r['tracking_losses']} | {r['ate_sim3_m']:.3f} | {r['ate_sim3_pct_of_distance']:.2f} | "
            f"{(r['r_rel_deg_per_100m'] or float('nan')):.3f} | {r['fps_process']:.1f} | {r['cpu_ms_per_frame']:.1f} | "
            f"{pf.get('frontend', 0):.1f} | {pf.get('pose', 0):.1f} | {pf.get('keyframe', 0):.1f} | "
            f"{pc.get('ba', 0):.1f} | {pc.get('marginalization', 0):.1f} | {r['decode_ms_per_frame']:.1f} |")
    out += ["", "Stage columns: frontend/pose/keyframe are wall ms per frame (keyframe work "
            "amortized); BA runs in a background thread (wall ms per solve), marginalization ms "
            "per keyframe. CPU ms/frame is the process CPU time (all threads) per frame: on a "
            "shared, overloaded machine it is the better measure of cost (fps ≈ 1000 / it when "
            "a core is free).", ""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seq", action="append", required=True, type=Path, help="sequence folder (repeat)")
    ap.add_argument("--preset", default=None)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--mode", choices=("background", "sync", "both"), default="both",
                    help="window BA in a worker thread (the default of the library), in the "
                    "tracking thread (deterministic), or both")
    ap.add_argument("--out", type=Path, default=Path("bench/results/vo.md"))
    ap.add_argument("--note", action="append", default=[],
                    help="provenance line for the report, e.g. how a synthetic sequence was made")
    args = ap.parse_args(argv)
    host = describe()
    rows = []
    modes = {"background": [True], "sync": [False], "both": [True, False]}[args.mode]
    for s, background in [(s, b) for s in args.seq for b in modes]:
        r = run_sequence(s, args.preset, background, args.max_frames)
        print(json.dumps({k: r[k] for k in ("name", "background_ba", "frames", "ate_sim3_pct_of_distance",
                                             "r_rel_deg_per_100m", "fps_process", "cpu_ms_per_frame",
                                             "keyframes", "tracking_losses")}))
        rows.append(r)
    command = command_line("bench.vo_accuracy", argv)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(to_markdown(rows, command, host, args.note))
    args.out.with_suffix(".json").write_text(json.dumps({"command": command, "machine": host,
                                                         "results": rows}, indent=2, default=float) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
