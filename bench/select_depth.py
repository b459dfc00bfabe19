"""Depth-model selection by the rule committed with the candidates' configs (issue #16).

The rule (written in ``training/configs/experiments/train_depth_v3_log.yaml`` and ``…_v3_dfrac.yaml`` before any
candidate's number was seen):

* candidates: the **EMA** weights of each training run at the given steps, exported to float32
  ONNX (``metricslam export --weights ema``);
* score: :func:`landmark_depth.summary`'s ``worst_abs_log_ratio`` (the worst |log median
  z_net/z_tri| over the bins 5–10, 10–20, 20–40, 40–60 m with ≥ 20 corners) on every validation
  sequence, and the **max over the sequences**; the lowest score wins;
* guard: the single-image LiDAR median ratio on the LiDAR validation folder
  (:func:`depth_accuracy.evaluate_lidar`) within [0.9, 1.1];
* the winner replaces the default only if its score beats the default's on the same benchmark.

The raw (optimizer) weights of the same checkpoints are scored too, for the spread between
checkpoints that the moving average is meant to damp; they are never candidates.

Example::

    .venv/bin/python -m bench.select_depth --run runs/depth_v3_log --run runs/depth_v3_dfrac \\
        --steps 3000 4000 5000 6000 --data ../shared/data --out bench/results/depth_v3_selection
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from bench.depth_accuracy import evaluate_lidar
from bench.landmark_depth import evaluate, summary
from bench.machine import command_line, describe, write_results
from metricslam.depth import DEFAULT_MODEL_PATH, DepthModel

#: validation sequences of issue #16 (relative to --data): (sequence folder, ground-truth poses)
VALIDATION = (("kitti_raw_stereo/sequences/2011_09_26_drive_0013", "kitti_raw_stereo/poses/2011_09_26_drive_0013.txt"),
              ("kitti_odometry/sequences/06", "kitti_odometry/poses/06.txt"))
LIDAR_VALIDATION = "kitti_raw_stereo/sequences/2011_09_26_drive_0013"
LIDAR_GUARD = (0.9, 1.1)


def export(run_dir: Path, step: int, weights: str, out_dir: Path) -> Path:
    """``run_dir/step_XXXXXX.pt`` → ``out_dir/<run>_<step>_<weights>.onnx`` (kept if present)."""
    out = out_dir / f"{run_dir.name}_{step}_{weights}.onnx"
    if not out.is_file():
        ckpt = run_dir / f"step_{step:06d}.pt"
        subprocess.run([str(Path(sys.executable).parent / "metricslam"), "export", str(ckpt), "--out", str(out),
                        "--weights", weights], check=True, capture_output=True, text=True)
    return out


def lidar_median(model_path: Path, data: Path) -> dict:
    args = SimpleNamespace(lidar_frames=(0, None), frame_step=2, min_depth_m=1.0, max_depth_m=80.0,
                           camera_height_m=1.65, slam_min_depth_m=10.0)
    res = evaluate_lidar(DepthModel.load(model_path, threads=1), data / LIDAR_VALIDATION, args)
    return {"median_ratio": res["model"]["median_ratio"], "abs_rel": res["model"]["abs_rel"],
            "by_range": {k: v["median_ratio"] for k, v in res["model_by_range"].items()}}


def score(model_path: Path, data: Path, label: str) -> dict:
    seqs = [(str(data / s), str(data / g)) for s, g in VALIDATION]
    corners = evaluate(seqs, model_path, label)
    per_seq = summary(corners)
    worst = [v["worst_abs_log_ratio"] for v in per_seq.values()]
    lidar = lidar_median(model_path, data)
    bins = {name: {b: res["network"][b]["median"] for b in res["network"]}
            for name, res in corners["sequences"].items()}
    return {"label": label, "model": str(model_path), "score": max(w if w is not None else np.inf for w in worst),
            "per_sequence": per_seq, "bins": bins, "lidar": lidar,
            "guard_ok": LIDAR_GUARD[0] <= lidar["median_ratio"] <= LIDAR_GUARD[1]}


def slam_check(model_path: Path, data: Path, workdir: Path) -> dict:
    """``metricslam run --deterministic`` (default settings otherwise) + ``metricslam eval`` on every
    validation sequence: scale error (%) and ATE SE(3) (m). Reported beside the rule, never used by it."""
    out = {}
    exe = str(Path(sys.executable).parent / "metricslam")
    for seq, gt in VALIDATION:
        name = Path(seq).name
        est = workdir / f"{model_path.stem}_{name}.txt"
        ev = est.with_suffix(".json")
        subprocess.run([exe, "run", str(data / seq), "--deterministic", "--no-progress", "--model", str(model_path),
                        "--out", str(est)], check=True, capture_output=True, text=True)
        subprocess.run([exe, "eval", "--gt", str(data / gt), "--est", str(est), "--json", str(ev)], check=True,
                       capture_output=True, text=True)
        res = json.loads(ev.read_text())  # one --gt/--est pair: the flat result
        out[name] = {"scale_error_pct": res["scale_error_pct"], "scale_ratio": res["scale_ratio"],
                     "ate_rmse_m": res["ate_rmse_m"]}
    return out


def score_slam_rule(model_path: Path, data: Path, label: str, workdir: Path) -> dict:
    """The v3-ft rule (``training/configs/experiments/train_depth_v3ft.yaml``): SLAM scale error on every validation
    drive (score = the largest) and the landmark-weighted corner ratio per drive."""
    seqs = [(str(data / s), str(data / g)) for s, g in VALIDATION]
    corners = summary(evaluate(seqs, model_path, label, oracle=False, slam=True))
    slam = slam_check(model_path, data, workdir)
    return {"label": label, "model": str(model_path), "slam": slam,
            "score": max(v["scale_error_pct"] for v in slam.values()),
            "vo_weighted": {k: v["vo_weighted_abs_log_ratio"] for k, v in corners.items()}}


def apply_slam_rule(default: dict, candidates: list[dict], max_06_pct: float = 5.0) -> dict | None:
    """Eligible: KITTI 06 scale error <= ``max_06_pct`` and the landmark-weighted corner ratio no
    worse than the default's on every drive; the lowest score wins (None if none is eligible)."""
    for c in candidates:
        c["eligible"] = (c["slam"]["06"]["scale_error_pct"] <= max_06_pct
                         and all(c["vo_weighted"][k] <= default["vo_weighted"][k] for k in default["vo_weighted"]))
    eligible = [c for c in candidates if c["eligible"]]
    return min(eligible, key=lambda c: c["score"]) if eligible else None


def slam_rule_markdown(report: dict) -> str:
    from bench.make_results import slam_rule_table  # the results page renders the same table

    return (f"# Depth v3-ft selection (rule in training/configs/experiments/train_depth_v3ft.yaml)\n\nCommand: `{report['command']}`  \n"
            f"Machine: {report['machine']}\n\n{slam_rule_table(report)}\n"
            + (f"\nScore (the larger scale error) {report['winner']['score']:.1f} % vs the shipped model's "
               f"{report['default']['score']:.1f} %.\n" if report["winner"] else ""))


def score_v3m_rule(model_path: Path, data: Path, label: str, workdir: Path) -> dict:
    """The v3m rule (``training/configs/experiments/train_depth_v3m.yaml``): SLAM scale error on
    every validation drive (score = the largest); what the scale factors consume
    (``bench/scale_measurements.py``, stereo reference) is reported beside it."""
    from bench.scale_measurements import evaluate as consumed

    slam = slam_check(model_path, data, workdir)
    seen = consumed([str(data / s) for s, _ in VALIDATION], str(model_path))
    return {"label": label, "model": str(model_path), "slam": slam,
            "score": max(v["scale_error_pct"] for v in slam.values()),
            "consumed": {name: {"measured_over_true": r["stereo"]["measured_over_true_median"],
                                "bins": {b: v["net_over_ref"] for b, v in r["stereo"]["bins"].items()},
                                "fraction": {b: v["fraction"] for b, v in r["stereo"]["bins"].items()}}
                         for name, r in seen["sequences"].items()}}


def apply_max_rule(default: dict, candidates: list[dict], max_pct: float = 10.0) -> dict | None:
    """Eligible: every validation drive's SLAM scale error <= ``max_pct``; the lowest score wins."""
    for c in candidates:
        c["eligible"] = all(v["scale_error_pct"] <= max_pct for v in c["slam"].values())
    eligible = [c for c in candidates if c["eligible"]]
    return min(eligible, key=lambda c: c["score"]) if eligible else None


def v3m_markdown(report: dict) -> str:
    names = list(report["default"]["slam"])
    bins = ("10-20", "20-40", "40-60", ">60")
    head = ("| model | " + " | ".join(f"{n} scale error" for n in names)
            + " | " + " | ".join(f"{n[-4:]} measured/true" for n in names)
            + " | " + " | ".join(f"{n[-4:]} net/ref {b} m" for n in names for b in bins) + " | eligible |")
    lines = [f"# Depth v3m selection (rule in training/configs/experiments/train_depth_v3m.yaml)\n\n"
             f"Command: `{report['command']}`  \nMachine: {report['machine']}\n",
             "Score: the larger `metricslam run --deterministic` scale error of the two validation drives. "
             "measured/true and net/ref: what the SLAM's scale factors consume (bench/scale_measurements.py, "
             "stereo reference; median over keyframes, and per range bin of the landmarks' depth); reported, "
             "not used by the rule.\n", head, "|" + " --- |" * (head.count("|") - 1)]

    def row(r: dict, eligible: str) -> str:
        errs = " | ".join(f"{r['slam'][n]['scale_error_pct']:.1f} % (×{r['slam'][n]['scale_ratio']:.3f})" for n in names)
        meas = " | ".join(f"×{r['consumed'][n]['measured_over_true']:.3f}" for n in names)
        per = " | ".join("–" if r["consumed"][n]["bins"][b] is None else f"×{r['consumed'][n]['bins'][b]:.2f}"
                         for n in names for b in bins)
        return f"| {r['label']} | {errs} | {meas} | {per} | {eligible} |"

    lines.append(row(report["default"], "—"))
    for c in report["candidates"]:
        lines.append(row(c, "yes" if c["eligible"] else "no"))
    w = report["winner"]
    lines += ["", f"Winner by the rule: **{w['label'] if w else 'none eligible'}**"
              + (f" (score {w['score']:.1f} % vs the shipped model's {report['default']['score']:.1f} %; "
                 f"{'beats it' if report['replaces_default'] else 'does NOT beat it'})" if w else "") + "."]
    return "\n".join(lines) + "\n"


def markdown(report: dict) -> str:
    seq_names = list(report["default"]["bins"])
    bins = ("5-10", "10-20", "20-40", "40-60")
    head = ("| candidate | weights | score (max worst abs log) | "
            + " | ".join(f"{s[-4:]} {b} m" for s in seq_names for b in bins)
            + " | LiDAR median (0013) | abs-rel | guard |")
    lines = [f"# Depth v3 selection\n\nCommand: `{report['command']}`  \nMachine: {report['machine']}\n",
             "Score: the worst |log median(z_net/z_tri)| over the bins 5–60 m, max over 0013 and 06 "
             "(bench/landmark_depth.py); lower is better. Candidates are EMA weights; raw weights are "
             "shown for the spread only.\n", head, "|" + " --- |" * (head.count("|") - 1)]

    def row(r: dict, weights: str) -> str:
        cells = []
        for s in seq_names:
            for b in bins:
                m = r["bins"][s].get(b)
                cells.append(f"×{m:.2f}" if m else "–")
        return (f"| {r['label']} | {weights} | {r['score']:.3f} | " + " | ".join(cells)
                + f" | {r['lidar']['median_ratio']:.3f} | {r['lidar']['abs_rel']:.3f} | "
                f"{'ok' if r['guard_ok'] else 'FAIL'} |")

    if report.get("slam"):
        lines += ["", "SLAM check (reported, not used by the rule): `metricslam run --deterministic --model M`, "
                  "scale error % per validation sequence.", "", "| candidate | " + " | ".join(
                      report["slam"][next(iter(report["slam"]))]) + " |", "| --- |" + " --- |" * len(
                      report["slam"][next(iter(report["slam"]))])]
        for label, per in report["slam"].items():
            lines.append(f"| {label} | " + " | ".join(f"{v['scale_error_pct']:.1f} % (×{v['scale_ratio']:.3f})"
                                                      for v in per.values()) + " |")
        lines += ["", head, "|" + " --- |" * (head.count("|") - 1)]
    lines.append(row(report["default"], "shipped"))
    for r in report["candidates"]:
        lines.append(row(r, "ema"))
    for r in report["raw"]:
        lines.append(row(r, "raw"))
    w = report["winner"]
    lines += ["", f"**Winner by the rule:** {w['label'] if w else 'none passes the guard'}"
              + (f" (score {w['score']:.3f} vs the default's {report['default']['score']:.3f}; "
                 f"{'replaces the default' if report['replaces_default'] else 'does NOT beat the default'})" if w else "")]
    for run, spread in report["spread"].items():
        lines.append(f"- `{run}` spread over checkpoints (raw → EMA), per-sequence all-corner median z_net/z_tri "
                     f"range: {spread}")
    return "\n".join(lines) + "\n"


def spread_text(rows: list[dict]) -> str:
    out = []
    for name in rows[0]["bins"]:
        meds = [r["bins"][name]["all"] for r in rows if r["bins"][name].get("all")]
        out.append(f"{name} {min(meds):.3f}–{max(meds):.3f}")
    return ", ".join(out)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, help="training run folder (repeat)")
    p.add_argument("--steps", type=int, nargs="+", required=True, help="checkpoint steps to score")
    p.add_argument("--data", default="../shared/data")
    p.add_argument("--export-dir", default="runs/candidates")
    p.add_argument("--no-raw", action="store_true", help="skip the raw-weight rows")
    p.add_argument("--slam", action="store_true", help="also run SLAM with every EMA candidate (reported only)")
    p.add_argument("--rule", choices=("corners", "slam", "v3m"), default="corners",
                   help="corners: the v3 rule (worst corner bin); slam: the v3-ft rule (SLAM scale error); "
                        "v3m: SLAM scale error, every drive <= 10 %%")
    p.add_argument("--jobs", type=int, default=2, help="candidates scored in parallel (one thread each)")
    p.add_argument("--out", required=True, metavar="PREFIX")
    args = p.parse_args(argv)
    data, export_dir = Path(args.data), Path(args.export_dir)
    export_dir.mkdir(parents=True, exist_ok=True)
    if args.rule in ("slam", "v3m"):
        return main_slam_rule(args, argv, data, export_dir)
    report = {"command": command_line("bench.select_depth", argv),
              "machine": describe(), "default": score(DEFAULT_MODEL_PATH, data, "default (shipped)"),
              "candidates": [], "raw": [], "spread": {}}
    tasks = [(run, step, w) for run in map(Path, args.run) for step in args.steps
             if (run / f"step_{step:06d}.pt").is_file() for w in (("ema",) if args.no_raw else ("ema", "raw"))]
    paths = [export(run, step, w, export_dir) for run, step, w in tasks]
    with multiprocessing.get_context("spawn").Pool(args.jobs) as pool:
        scored = pool.starmap(score, [(path, data, f"{run.name}@{step}") for path, (run, step, _) in zip(paths, tasks)])
    for run in map(Path, args.run):
        rows_ema = [r for r, (rn, _, w) in zip(scored, tasks) if rn == run and w == "ema"]
        rows_raw = [r for r, (rn, _, w) in zip(scored, tasks) if rn == run and w == "raw"]
        report["candidates"] += rows_ema
        report["raw"] += rows_raw
        if rows_ema:
            report["spread"][run.name] = (f"raw {spread_text(rows_raw)}; " if rows_raw else "") \
                + f"EMA {spread_text(rows_ema)}"
    if args.slam:
        work = export_dir / "slam"
        work.mkdir(parents=True, exist_ok=True)
        models = [(report["default"]["label"], DEFAULT_MODEL_PATH)] + [(r["label"], Path(r["model"]))
                                                                      for r in report["candidates"]]
        with multiprocessing.get_context("spawn").Pool(args.jobs) as pool:
            runs = pool.starmap(slam_check, [(m, data, work) for _, m in models])
        report["slam"] = {label: res for (label, _), res in zip(models, runs)}
    passing = [r for r in report["candidates"] if r["guard_ok"]]
    report["winner"] = min(passing, key=lambda r: r["score"]) if passing else None
    report["replaces_default"] = bool(report["winner"] and report["winner"]["score"] < report["default"]["score"])
    text = markdown(report)
    print(text)
    write_results(args.out, report, text)
    return 0


def main_slam_rule(args, argv: list[str], data: Path, export_dir: Path) -> int:
    work = export_dir / "slam"
    work.mkdir(parents=True, exist_ok=True)
    tasks = [(run, step) for run in map(Path, args.run) for step in args.steps if (run / f"step_{step:06d}.pt").is_file()]
    models = [("default (shipped)", DEFAULT_MODEL_PATH)] + [
        (f"{run.name}@{step}", export(run, step, "ema", export_dir)) for run, step in tasks]
    scorer = score_v3m_rule if args.rule == "v3m" else score_slam_rule
    with multiprocessing.get_context("spawn").Pool(args.jobs) as pool:
        rows = pool.starmap(scorer, [(m, data, label, work) for label, m in models])
    report = {"command": command_line("bench.select_depth", argv), "rule": args.rule,
              "machine": describe(), "default": rows[0], "candidates": rows[1:]}
    if args.rule == "v3m":
        report["winner"] = apply_max_rule(report["default"], report["candidates"])
    else:
        report["winner"] = apply_slam_rule(report["default"], report["candidates"])
    report["replaces_default"] = bool(report["winner"] and report["winner"]["score"] < report["default"]["score"])
    text = v3m_markdown(report) if args.rule == "v3m" else slam_rule_markdown(report)
    print(text)
    write_results(args.out, report, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
