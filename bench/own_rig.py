"""One camera that is not KITTI's, before and after fine-tuning the depth network on it.

For a held-aside drive of the rig (a KITTI-layout folder with ``poses/00.txt``, e.g. one rendered
by ``metricslam synth --fx --baseline-m --height-m``) and each named depth model:

1. **SLAM** — ``metricslam run SEQ --deterministic --model M [--calib CAM.yaml]``, then
   ``metricslam eval`` against the drive's ground truth: scale error (%; ``|s − 1|`` of the
   Umeyama Sim(3) scale between the estimate and the truth, docs/evaluation.md), ATE after an
   SE(3) alignment (m, and % of the path length), ATE after Sim(3) (m: the trajectory's shape
   once its scale is forgiven), KITTI t_rel.
2. **Depth where the SLAM samples it** — :func:`bench.landmark_depth.evaluate` on the same drive
   (no SGBM oracle): median ``z_net / z_tri`` at corners tracked over 3 frames and triangulated
   with the ground-truth motion, per range bin (1 = right; 0.5 = reads half the distance); the
   ``depth_0`` check row scores the rendered depth the same way (tests the reference).

The page that explains the whole procedure, with every command: ``docs/own_camera.md``.
``--target-pct`` (default 5, issue #17) marks each model's scale error as within target or not.

Example::

    nice -n 15 .venv/bin/python -m bench.own_rig --seq runs/own_rig/eval_s4201_loop \\
        --calib runs/own_rig/my_camera.yaml \\
        --model before=shared/metricslam/models/depth_l3_int8.onnx \\
        --model after=runs/own_rig/depth_own_rig_int8.onnx --out bench/results/own_rig
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

from bench.accuracy import METRICSLAM, _shown
from bench.landmark_depth import BIN_LABELS
from bench.landmark_depth import evaluate as landmark_evaluate
from bench.machine import command_line, publish

#: what ``metricslam eval`` reports that the table shows (units in docs/evaluation.md)
EVAL_KEYS = ("scale_error_pct", "scale_ratio", "ate_rmse_m", "ate_rmse_sim3_m", "t_rel_pct",
             "path_length_m", "n_frames")


def run_and_score(name: str, seq: str, model: str, calib: str | None, workdir: Path) -> dict:
    """``metricslam run --deterministic`` with ``model`` on ``seq`` and ``metricslam eval`` of its
    poses; returns the commands, the eval metrics (or the error) and the run's counters."""
    est, stats, ev = workdir / f"{name}.txt", workdir / f"{name}_stats.json", workdir / f"{name}_eval.json"
    run = METRICSLAM + ["run", seq, "--deterministic", "--model", model, "--out", str(est), "--json", str(stats),
                        "--no-progress"] + (["--calib", calib] if calib else [])
    t0 = time.perf_counter()
    proc = subprocess.run(run, capture_output=True, text=True)
    out: dict = {"run_command": _shown(run), "run_wall_s": time.perf_counter() - t0}
    if proc.returncode != 0:
        return {**out, "error": (proc.stderr or proc.stdout)[-800:].strip()}
    s = json.loads(stats.read_text())
    out["run"] = {k: s.get(k) for k in ("keyframes", "tracking_losses", "preset", "fps", "pose_invalid",
                                        "interpolated")}
    out["run"].update({k: s.get("backend", {}).get(k) for k in ("loops_accepted", "loops_rejected")})
    gt = str(Path(seq) / "poses" / "00.txt")
    evaluate = METRICSLAM + ["eval", "--gt", gt, "--est", str(est), "--json", str(ev)]
    proc = subprocess.run(evaluate, capture_output=True, text=True)
    out["eval_command"] = _shown(evaluate)
    if proc.returncode != 0:
        return {**out, "error": (proc.stderr or proc.stdout)[-800:].strip()}
    report = json.loads(ev.read_text())  # one sequence: its metrics are the top-level keys
    row = report["per_sequence"][0] if "per_sequence" in report else report
    metrics = {k: row.get(k) for k in EVAL_KEYS}
    if metrics["ate_rmse_m"] is not None and metrics["path_length_m"]:
        metrics["ate_pct_of_path"] = 100.0 * metrics["ate_rmse_m"] / metrics["path_length_m"]
    out["eval"] = metrics
    return out


def evaluate(seq: str, models: list[tuple[str, str]], calib: str | None, workdir: Path,
             target_pct: float) -> dict:
    """Every model on ``seq``: SLAM (:func:`run_and_score`) and corner depth ratios per range bin."""
    gt = str(Path(seq) / "poses" / "00.txt")
    rows = []
    for name, path in models:
        row = {"name": name, "model": path, **run_and_score(name, seq, path, calib, workdir)}
        corners = landmark_evaluate([(seq, gt)], path, name, oracle=False)
        res = next(iter(corners["sequences"].values()))
        row["model_id"], row["weights_precision"] = corners["model"]["model_id"], corners["model"]["weights_precision"]
        row["corners"] = {"pairs": res["pairs"], "n": res["corners"], "network": res["network"],
                          "depth_0": res["depth_0"], "eval_s": res["eval_s"]}
        err = (row.get("eval") or {}).get("scale_error_pct")
        row["within_target"] = None if err is None else bool(err <= target_pct)
        rows.append(row)
    return {"seq": seq, "calib": calib, "target_scale_error_pct": target_pct, "models": rows}


def _f(x, fmt: str) -> str:
    return "–" if x is None else format(x, fmt)


def markdown(result: dict, command: str, machine: str) -> str:
    """Table 1: SLAM per model; table 2: corner depth ratio per range bin per model."""
    target = result["target_scale_error_pct"]
    lines = [f"# Own rig: {Path(result['seq']).name}, before and after fine-tuning", "",
             f"Command: `{command}`  ", f"Machine: {machine}  ",
             f"Load average when the runs started: {result.get('load_at_start', '?')}  ",
             f"Calibration passed to `metricslam run`: `{result['calib']}`" if result["calib"] else
             "Intrinsics: the folder's calib.txt", "",
             f"| model | weights | scale error (target ≤ {target:g} %) | scale | ATE SE(3) | ATE % of path | "
             "ATE Sim(3) | t_rel | path | keyframes | loops accepted / rejected |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in result["models"]:
        if "error" in r:
            lines.append(f"| {r['name']} (`{r['model']}`) | {r.get('weights_precision', '?')} | failed: "
                         f"{r['error'][-200:]} | | | | | | | | |")
            continue
        e, mark = r["eval"], {True: "within", False: "above", None: "?"}[r["within_target"]]
        lines.append(f"| {r['name']} (`{r['model']}`) | {r['weights_precision']} | **{e['scale_error_pct']:.1f} %** "
                     f"({mark}) | ×{e['scale_ratio']:.3f} | {e['ate_rmse_m']:.2f} m | {_f(e.get('ate_pct_of_path'), '.2f')} % | "
                     f"{e['ate_rmse_sim3_m']:.2f} m | {_f(e['t_rel_pct'], '.1f')} % | {e['path_length_m']:.0f} m | "
                     f"{r['run']['keyframes']} | {r['run']['loops_accepted']} / {r['run']['loops_rejected']} |")
    lines += ["", "Depth network at ground-truth-triangulated corners of the same drive (median z_net / z_tri, "
              "corners in brackets; bench/landmark_depth.py, no SGBM oracle):", "",
              "| model | " + " | ".join(f"{b} m" for b in BIN_LABELS) + " | all |",
              "| --- |" + " --- |" * (len(BIN_LABELS) + 1)]
    cell = lambda s: "–" if not s["n"] else f"×{s['median']:.2f} ({s['n']})"  # noqa: E731
    for r in result["models"]:
        lines.append(f"| {r['name']} | " + " | ".join(cell(r["corners"]["network"][b]) for b in [*BIN_LABELS, "all"])
                     + " |")
    first = result["models"][0]["corners"]
    if first.get("depth_0"):
        lines.append("| check: rendered depth_0 | " + " | ".join(cell(first["depth_0"][b])
                                                                for b in [*BIN_LABELS, "all"]) + " |")
    lines += ["", "Commands of each run:", ""]
    for r in result["models"]:
        lines += [f"* {r['name']}: `{r['run_command']}`" + (f"; `{r['eval_command']}`" if "eval_command" in r else "")]
    return "\n".join(lines) + "\n"


def _named(text: str) -> tuple[str, str]:
    name, sep, path = text.partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(f"--model takes NAME=PATH.onnx, got {text!r}")
    return name, path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", required=True, help="held-aside KITTI-layout drive with poses/00.txt")
    p.add_argument("--model", type=_named, action="append", required=True, metavar="NAME=PATH.onnx",
                   help="a depth model to score, in table order (repeat)")
    p.add_argument("--calib", help="calibration YAML for metricslam run --calib (default: the folder's calib.txt)")
    p.add_argument("--target-pct", type=float, default=5.0, help="scale error target, %% (default 5)")
    p.add_argument("--keep", metavar="DIR", help="keep the estimates and run statistics here")
    p.add_argument("--out", metavar="PREFIX", help="write PREFIX.json and PREFIX.md")
    args = p.parse_args(argv)
    cv2.setNumThreads(1)
    command = command_line("bench.own_rig", argv)
    load = "/".join(f"{x:.2f}" for x in os.getloadavg())
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(args.keep or tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        result = evaluate(args.seq, args.model, args.calib, workdir, args.target_pct)
    result["load_at_start"] = load
    publish(args.out, result, command, markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
