"""Issue #32 item 3: the largest frame-to-frame jump of the live pose stream and of the continuous
odometry stream, against the true per-frame motion.

For every sequence, runs ``metricslam run --deterministic`` with ``--live-out`` (the poses as the
SLAM service publishes them on ``…/pose``) and ``--continuous-out`` (``…/odom``,
:mod:`metricslam.trajectory.continuous`), and once more without the two streams to check that the
optimized trajectory (``--out``) is byte-identical with and without the observer. Per stream:
the largest step ``|p_k − p_{k−1}|`` (m, world frame; the live stream is metric, so no alignment
is applied), where it happens, and the largest per-frame ratio step / true step (frames whose
true step is at least ``--min-true-step`` m). The target: the continuous stream's largest step
within 2x the largest true per-frame motion.

Example::

    .venv/bin/python -m bench.pose_jumps \\
        --seq kitti06=../shared/data/kitti_odometry/sequences/06:../shared/data/kitti_odometry/poses/06.txt \\
        --seq 0013=../shared/data/kitti_raw_stereo/sequences/2011_09_26_drive_0013:../shared/data/kitti_raw_stereo/poses/2011_09_26_drive_0013.txt \\
        --out bench/results/pose_jumps
"""

from __future__ import annotations

import argparse
import filecmp
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from bench.accuracy import METRICSLAM
from bench.machine import command_line, publish
from metricslam.trajectory.io import read_kitti_poses


def steps_m(T_world_cam: np.ndarray) -> np.ndarray:
    """(N-1,) distances (m) between consecutive positions of (N, 4, 4) poses."""
    return np.linalg.norm(np.diff(T_world_cam[:, :3, 3], axis=0), axis=1)


def jump_stats(T_world_cam: np.ndarray, true_steps_m: np.ndarray, min_true_step_m: float) -> dict:
    """Largest step (m) of a stream, the frame it lands on, the positions' distance from the
    origin either side, and the largest per-frame step / true step."""
    steps = steps_m(T_world_cam)
    k = int(np.argmax(steps))
    moving = true_steps_m >= min_true_step_m
    ratios = steps[moving] / true_steps_m[moving]
    r = int(np.argmax(ratios)) if len(ratios) else 0
    return {"max_step_m": float(steps[k]), "max_step_frame": k + 1,
            "range_before_after_m": [float(np.linalg.norm(T_world_cam[k, :3, 3])),
                                     float(np.linalg.norm(T_world_cam[k + 1, :3, 3]))],
            "true_step_there_m": float(true_steps_m[k]),
            "max_step_over_true": float(ratios[r]) if len(ratios) else None,
            "max_step_over_true_frame": int(np.flatnonzero(moving)[r]) + 1 if len(ratios) else None,
            "p99_step_m": float(np.percentile(steps, 99))}


def run_sequence(name: str, seq: str, gt: str, workdir: Path, horizon_s: float | None,
                 min_true_step_m: float, check_unchanged: bool) -> dict:
    out, live, cont, stats = (workdir / f"{name}_{leaf}" for leaf in ("est.txt", "live.txt", "cont.txt", "stats.json"))
    cmd = [*METRICSLAM, "run", seq, "--deterministic", "--no-progress", "--out", str(out), "--json", str(stats),
           "--live-out", str(live), "--continuous-out", str(cont),
           *([] if horizon_s is None else ["--continuous-horizon", str(horizon_s)])]
    subprocess.run(cmd, check=True)
    T_true, T_live, T_cont = read_kitti_poses(gt), read_kitti_poses(live), read_kitti_poses(cont)
    n = min(len(T_true), len(T_live))
    T_true, T_live, T_cont = T_true[:n], T_live[:n], T_cont[:n]
    true_steps = steps_m(T_true)
    gap = np.linalg.norm(T_cont[:, :3, 3] - T_live[:, :3, 3], axis=1)
    run_stats = json.loads(stats.read_text())
    result = {"sequence": seq, "frames": n, "true_max_step_m": float(true_steps.max()),
              "true_median_step_m": float(np.median(true_steps)),
              "live": jump_stats(T_live, true_steps, min_true_step_m),
              "continuous": jump_stats(T_cont, true_steps, min_true_step_m),
              "continuous_minus_live_max_m": float(gap.max()), "continuous_minus_live_last_m": float(gap[-1]),
              "continuous_stats": run_stats.get("continuous"),
              "corrections_applied": run_stats.get("corrections_applied")}
    result["continuous_max_over_true_max"] = result["continuous"]["max_step_m"] / result["true_max_step_m"]
    result["live_max_over_true_max"] = result["live"]["max_step_m"] / result["true_max_step_m"]
    result["within_2x"] = result["continuous_max_over_true_max"] <= 2.0
    if check_unchanged:
        plain = workdir / f"{name}_est_plain.txt"
        subprocess.run([*METRICSLAM, "run", seq, "--deterministic", "--no-progress", "--out", str(plain)], check=True)
        result["optimized_byte_identical_without_streams"] = filecmp.cmp(out, plain, shallow=False)
    return result


def render(result: dict, command: str, machine: str) -> str:
    lines = ["# Pose jumps: live stream vs continuous odometry (issue #32 item 3)", "",
             f"Command: `{command}`", f"Machine: {machine}", "", result.get("note", ""), "",
             "| sequence | true max step | live max step (frame) | live / true | continuous max step (frame) "
             "| continuous / true | within 2x | optimized unchanged |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    lines += [row(name, r) for name, r in result["sequences"].items()]
    return "\n".join(lines) + "\n"


def row(name: str, r: dict) -> str:
    """One table row (also what ``bench/make_results.py`` renders)."""
    live, cont = r["live"], r["continuous"]
    same = r.get("optimized_byte_identical_without_streams")
    return (f"| {name} | {r['true_max_step_m']:.2f} m | {live['max_step_m']:.2f} m ({live['max_step_frame']}) | "
            f"{r['live_max_over_true_max']:.2f} | {cont['max_step_m']:.2f} m ({cont['max_step_frame']}) | "
            f"{r['continuous_max_over_true_max']:.2f} | {'yes' if r['within_2x'] else 'no'} | "
            f"{'-' if same is None else ('yes' if same else 'NO')} |")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", action="append", required=True, metavar="NAME=SEQ_DIR:GT.txt")
    p.add_argument("--horizon", type=float, default=None, metavar="S", help="--continuous-horizon of the runs")
    p.add_argument("--min-true-step", type=float, default=0.05, metavar="M",
                   help="frames whose true step is shorter are left out of the per-frame ratio")
    p.add_argument("--no-check-unchanged", action="store_true",
                   help="skip the second run that checks --out is byte-identical without the streams")
    p.add_argument("--keep", metavar="DIR", help="keep the pose files here (default: a temporary folder)")
    p.add_argument("--note", default="", help="a line for the results file (e.g. what shared the CPU)")
    p.add_argument("--out", metavar="OUT", help="write OUT.json and OUT.md")
    args = p.parse_args(argv)
    command = command_line("bench.pose_jumps", argv)
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(args.keep or tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        sequences = {}
        for spec in args.seq:
            name, rest = spec.split("=", 1)
            seq, gt = rest.rsplit(":", 1)
            sequences[name] = run_sequence(name, seq, gt, workdir, args.horizon, args.min_true_step,
                                           not args.no_check_unchanged)
    result = {"note": args.note, "horizon_s": args.horizon, "sequences": sequences}
    publish(args.out, result, command, render)
    return 0 if all(r["within_2x"] for r in sequences.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
