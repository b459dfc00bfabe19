"""Depth recipes v4-v8 (issue #31): leave-one-drive-out folds, seeds and their ensemble, scored and
decided by the rule committed before any of the recipe's numbers was seen
(``docs/history/rule_depth_<recipe>.md``; v5-v8 reuse v4's step and form, each rule its own verdict).

Folds (each scored only by runs that never trained on its drive; ``R`` is ``--recipe``):

* ``06``   — runs ``R_all_s*`` (KITTI 06 is never trained on): ``metricslam run --deterministic``
  scale error against the KITTI poses, corner check per range bin (``bench/landmark_depth.py``);
* ``0013`` — runs ``R_no0013_s*``: the same against the GPS/INS poses;
* ``1405`` — runs ``R_no1405_s*`` on residential_1405 (no poses): ``bench/scale_measurements.py``
  against the drive's own stereo; the score is |median(measured / true) − 1| in %.

For every step, each finished seed is exported (EMA weights, float32) and scored, and so is the
ensemble of the fold's finished seeds (one ONNX graph, the mean of their L3 d_frac). The current
default is scored on the same folds. Scores are cached in ``--work`` (``scores.json``), so a rerun
after more runs finish only scores what is new.

Example::

    .venv/bin/python -m bench.depth_folds --recipe v5 --rule ship --out bench/results/depth_v5_ship
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from bench.machine import command_line, describe, write_results
from metricslam.depth import DEFAULT_MODEL_PATH

#: the recipes with committed rules
RECIPES = ("v4", "v5", "v6", "v7", "v8")
#: fold name -> (run prefix after "<recipe>_", kind, sequence folder, ground truth) relative to --data
FOLDS = {
    "06": ("all", "slam", "kitti_odometry/sequences/06", "kitti_odometry/poses/06.txt"),
    "0013": ("no0013", "slam", "kitti_raw_stereo/sequences/2011_09_26_drive_0013",
             "kitti_raw_stereo/poses/2011_09_26_drive_0013.txt"),
    "1405": ("no1405", "stereo", "kitti_raw_stereo/sequences/2011_09_26_residential_1405", None),
}
#: the rules' constants (docs/history/rule_depth_v4.md, shared by v5, v6 and rule_depth_ship.md)
STEP_TIE_POINTS, SPREAD_LIMIT_POINTS, DEFAULT_SINGLE_SEED = 0.5, 3.0, 23
CORNER_BINS, STEREO_BINS = ("5-10", "10-20", "20-40", "40-60"), ("10-20", "20-40", "40-60")

EXE = str(Path(sys.executable).parent / "metricslam")
FOLD_SCORE_TEXT = ("Fold score: SLAM scale error (06, 0013: `metricslam run --deterministic` against the poses) or "
                   "|measured / true − 1| of the back end's scale measurements against the drive's own stereo "
                   "(1405, no poses). Seeds: EMA weights of each run; ensemble: the mean of the seeds' L3 d_frac "
                   "in one ONNX graph. Each fold is scored only by runs that never trained on its drive.")


def _run(args: list[str]) -> None:
    res = subprocess.run(args, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed ({res.returncode}): {res.stderr[-2000:]}")


def export_model(checkpoints: list[Path], out: Path) -> Path:
    """EMA weights of one checkpoint, or the ensemble of several, to float32 ONNX (kept if present)."""
    if not out.is_file():
        _run([EXE, "export", *map(str, checkpoints), "--out", str(out), "--weights", "ema"])
    return out


def slam_score(model: Path, seq: Path, gt: Path, work: Path, corners: bool) -> dict:
    """Scale error (%), scale ratio and ATE SE(3) of ``metricslam run --deterministic``; the corner
    check's per-bin median z_net/z_tri when ``corners``."""
    from bench.landmark_depth import evaluate as corner_check

    est = work / f"{model.stem}__{seq.name}.txt"
    ev = est.with_suffix(".json")
    _run([EXE, "run", str(seq), "--deterministic", "--no-progress", "--model", str(model), "--out", str(est)])
    _run([EXE, "eval", "--gt", str(gt), "--est", str(est), "--json", str(ev)])
    res = json.loads(ev.read_text())
    out = {"score_pct": float(res["scale_error_pct"]), "scale_ratio": float(res["scale_ratio"]),
           "ate_se3_m": float(res["ate_rmse_m"])}
    if corners:
        net = next(iter(corner_check([(str(seq), str(gt))], model, model.stem, oracle=False)["sequences"].values()))
        out["corners"] = {b: net["network"][b]["median"] for b in CORNER_BINS}
    return out


def stereo_score(model: Path, seq: Path) -> dict:
    """|median over keyframes of (robust scale measurement / stereo truth) − 1| (%), with the
    optimized keyframe scale over truth and net/stereo per range bin beside it."""
    from bench.scale_measurements import evaluate as consumed

    res = next(iter(consumed([str(seq)], str(model))["sequences"].values()))["stereo"]
    measured = float(res["measured_over_true_median"])
    return {"score_pct": abs(measured - 1.0) * 100.0, "measured_over_true": measured,
            "optimized_over_true": res["optimized_over_true_median"],
            "bins": {b: res["bins"][b]["net_over_ref"] for b in STEREO_BINS}}


class Scorer:
    """Cached scores, keyed by model file name and fold."""

    def __init__(self, data: Path, work: Path) -> None:
        self.data, self.work = data, work
        self.path = work / "scores.json"
        self.cache = json.loads(self.path.read_text()) if self.path.is_file() else {}

    def __call__(self, model: Path, fold: str, corners: bool) -> dict:
        key = f"{model.name}|{fold}|{int(corners)}"
        if key not in self.cache:
            _, kind, seq, gt = FOLDS[fold]
            print(f"scoring {model.name} on fold {fold}", flush=True)
            self.cache[key] = (slam_score(model, self.data / seq, self.data / gt, self.work, corners)
                               if kind == "slam" else stereo_score(model, self.data / seq))
            self.path.write_text(json.dumps(self.cache, indent=1))
        return self.cache[key]


def score_folds(recipe: str, runs: Path, steps: list[int], seeds: list[int], scorer: Scorer, work: Path,
                folds: tuple[str, ...] = tuple(FOLDS)) -> dict:
    """``{fold: {step: {"seeds": {seed: score}, "ensemble": score | None, "members": [...]}}}``."""
    out: dict = {}
    for fold in folds:
        run, kind, _, _ = FOLDS[fold]
        prefix = f"{recipe}_{run}"
        out[fold] = {}
        for step in steps:
            ckpts = {str(s): runs / f"{prefix}_s{s}" / f"step_{step:06d}.pt" for s in seeds}
            ckpts = {s: p for s, p in ckpts.items() if p.is_file()}
            if not ckpts:
                continue
            row = {"members": sorted(ckpts), "seeds": {}, "ensemble": None}
            for s, p in ckpts.items():
                model = export_model([p], work / f"{prefix}_s{s}_{step}.onnx")
                row["seeds"][s] = scorer(model, fold, corners=False)
            if len(ckpts) > 1:
                tag = "".join(str(s) for s in sorted(ckpts))
                model = export_model(list(ckpts.values()), work / f"{prefix}_ens{tag}_{step}.onnx")
                row["ensemble"] = scorer(model, fold, corners=kind == "slam")
            out[fold][str(step)] = row
    return out


def _ensemble_or_only(row: dict) -> dict:
    return row["ensemble"] if row["ensemble"] is not None else next(iter(row["seeds"].values()))


def decide(folds: dict, default: dict, beat_default: bool = True) -> dict:
    """The rule of ``docs/history/rule_depth_v4.md`` (v5, v6: the same) applied to the scores; ``beat_default``
    False: ``rule_depth_ship.md`` (same step and form; shipping is its KITTI-06 guard, not the default's score)."""
    steps = sorted({step for rows in folds.values() for step in rows}, key=int)
    worst = {}
    for step in steps:
        scores = {f: _ensemble_or_only(rows[step])["score_pct"] for f, rows in folds.items() if step in rows}
        worst[step] = {"worst_pct": max(scores.values()), "folds": sorted(scores)}
    if not worst:
        return {"step": None, "reason": "no checkpoint finished"}
    best = min(w["worst_pct"] for w in worst.values())
    step = max((s for s, w in worst.items() if w["worst_pct"] <= best + STEP_TIE_POINTS), key=int)
    spread = {f: (max(v["score_pct"] for v in rows[step]["seeds"].values())
                  - min(v["score_pct"] for v in rows[step]["seeds"].values()), len(rows[step]["seeds"]))
              for f, rows in folds.items() if step in rows}
    ensemble = any(points > SPREAD_LIMIT_POINTS for points, n in spread.values() if n > 1)
    if ensemble:
        candidate = worst[step]["worst_pct"]
    else:
        single = str(DEFAULT_SINGLE_SEED)
        candidate = max(rows[step]["seeds"][single]["score_pct"] for rows in folds.values()
                        if step in rows and single in rows[step]["seeds"])
    default_worst = max(v["score_pct"] for f, v in default.items() if f in worst[step]["folds"])
    return {"worst_by_step": worst, "step": step, "spread_points": {f: s for f, (s, _) in spread.items()},
            "seeds_per_fold": {f: n for f, (_, n) in spread.items()}, "ship": "ensemble" if ensemble else
            f"seed {DEFAULT_SINGLE_SEED}", "candidate_worst_pct": candidate, "default_worst_pct": default_worst,
            "replaces_default": candidate < default_worst if beat_default else None}


def fold_table(report: dict) -> str:
    """Per fold and step: each seed's score, the spread, the ensemble's score and its per-bin detail."""
    seeds = report["seeds"]
    lines = ["| fold | step | " + " | ".join(f"seed {s}" for s in seeds) + " | spread | ensemble | ensemble detail |",
             "|" + " --- |" * (5 + len(seeds))]
    for fold, rows in report["folds"].items():
        for step, row in rows.items():
            cells = [f"{row['seeds'][s]['score_pct']:.1f} %" if s in row["seeds"] else "–" for s in seeds]
            vals = [v["score_pct"] for v in row["seeds"].values()]
            ens = row["ensemble"]
            detail = ""
            if ens and "corners" in ens:
                detail = ("corners " + " / ".join("–" if ens["corners"][b] is None else f"×{ens['corners'][b]:.2f}"
                                                  for b in CORNER_BINS)
                          + f" (m: {', '.join(CORNER_BINS)}); ATE SE(3) {ens['ate_se3_m']:.2f} m")
            elif ens and "bins" in ens:
                detail = ("net/stereo " + " / ".join("–" if ens["bins"][b] is None else f"×{ens['bins'][b]:.2f}"
                                                     for b in STEREO_BINS) + f" (m: {', '.join(STEREO_BINS)})")
            lines.append(f"| {fold} | {step} | " + " | ".join(cells) + f" | {max(vals) - min(vals):.1f} | "
                         + (f"{ens['score_pct']:.1f} %" if ens else "–") + f" | {detail} |")
    return "\n".join(lines)


def decision_line(report: dict) -> str:
    """The rule's decision in one paragraph, with the current default's fold scores."""
    d, dec = report["default"], report["decision"]
    default = (f"The default it was measured against (`{report['default_model']}`, never trained on these "
               "drives): " + ", ".join(f"{f} {v['score_pct']:.1f} %" for f, v in d.items()) + ".")
    if dec.get("step") is None:
        return f"{default} Decision: none ({dec.get('reason')})."
    return (f"{default} Decision by the rule: step **{dec['step']}** (worst fold by step: "
            + ", ".join(f"{s}: {w['worst_pct']:.1f} %" for s, w in dec["worst_by_step"].items())
            + "); seed spread at that step: "
            + ", ".join(f"{f} {p:.1f} points ({dec['seeds_per_fold'][f]} seeds)" for f, p in dec["spread_points"].items())
            + f"; the candidate's form: **{dec['ship']}**; its worst fold {dec['candidate_worst_pct']:.1f} % against the default's "
            f"{dec['default_worst_pct']:.1f} % on the same folds" + (
                "; under rule_depth_ship.md that does not decide: the all-drive candidate ships if its int8 copy "
                f"meets the KITTI-06 guard (`bench/results/depth_{report.get('recipe')}_ship_guard.md`)." if dec["replaces_default"] is None
                else ": replaces the default." if dec["replaces_default"] else ": does NOT replace the default."))


def markdown(report: dict) -> str:
    r = report.get("recipe", "v4")
    lines = [f"# Depth {r}: leave-one-drive-out folds (bench/depth_folds.py)", "",
             f"Rule: docs/history/rule_depth_{report.get('rule', r)}.md (committed before any number it decides on).  ",
             f"Command: `{report['command']}`  ", f"Machine: {report['machine']}", ""]
    if report.get("note"):
        lines += [report["note"], ""]
    lines += [FOLD_SCORE_TEXT, "", fold_table(report), "", decision_line(report)]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--recipe", choices=RECIPES, required=True, help="which recipe's runs and rule")
    ap.add_argument("--runs", type=Path, default=Path("runs"), help="folder of the <recipe>_* run folders")
    ap.add_argument("--work", type=Path, default=None, help="exported models, trajectories, cache "
                    "(default: runs/<recipe>_eval)")
    ap.add_argument("--folds", nargs="+", choices=tuple(FOLDS), default=list(FOLDS),
                    help="score only these folds (a fold left out is reported as not measured)")
    ap.add_argument("--steps", type=int, nargs="+", default=[2000, 2500, 3000])
    ap.add_argument("--seeds", type=int, nargs="+", default=[23, 24, 25])
    ap.add_argument("--baseline", type=Path, default=DEFAULT_MODEL_PATH,
                    help="the model a candidate must beat (default: the shipped default; once a recipe ships, a "
                         "copy of the model it replaced)")
    ap.add_argument("--rule", choices=("recipe", "ship"), default="recipe", help="recipe: the recipe's own rule "
                    "(beat the default's worst fold); ship: docs/history/rule_depth_ship.md")
    ap.add_argument("--note", default="")
    ap.add_argument("--out", type=Path, required=True, help="results path without extension (.json and .md)")
    args = ap.parse_args(argv)
    args.work = args.work or Path("runs") / f"{args.recipe}_eval"
    args.work.mkdir(parents=True, exist_ok=True)
    scorer = Scorer(args.data, args.work)
    default = {f: scorer(args.baseline, f, corners=FOLDS[f][1] == "slam") for f in FOLDS}
    folds = score_folds(args.recipe, args.runs, args.steps, args.seeds, scorer, args.work, tuple(args.folds))
    report = {"command": command_line("bench.depth_folds"), "machine": describe(), "note": args.note,
              "recipe": args.recipe, "rule": args.recipe if args.rule == "recipe" else "ship",
              "seeds": [str(s) for s in args.seeds],
              "default_model": args.baseline.name, "default": default, "folds": folds,
              "decision": decide(folds, default, beat_default=args.rule == "recipe")}
    text = markdown(report)
    write_results(args.out, report, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
