"""Table 1 — accuracy: full metricslam vs ``--no-scale``, side by side, same run.

For every sequence (KITTI layout with ground truth) runs ``metricslam run`` twice — learned scale
(default) and ``--no-scale`` — then ``metricslam eval`` on three estimates:

* ``metric``: the metricslam trajectory as written (no ground truth touches it);
* ``noscale``: the ``--no-scale`` trajectory as written (its scale is whatever the monocular
  initialization chose);
* ``noscale_sim3``: the ``--no-scale`` trajectory after a Sim(3) Umeyama alignment onto the
  ground truth — an *oracle* scale from ground truth, the best a monocular system without learned
  scale can do. t_rel / r_rel of this row are computed on the aligned poses.

Then pooled and mean-of-sequences numbers per variant via one ``metricslam eval`` call with
several ``--gt/--est`` pairs, over all sequences and over those the depth network never saw.

By default runs are not deterministic (VO bundle adjustment and the global graph run in their own
threads, as live); ``--run-args --deterministic`` makes them so. ``--repeats N`` runs every sequence and
mode N times; each cell is then ``mean ± sd`` (sample standard deviation over the N runs; pooled
numbers are pooled within each repeat, then averaged), and the JSON keeps every run's row
(``sequences[i].repeats``, ``pooled_repeats``) besides the per-metric ``summary``.

Example::

    nice -n 5 .venv/bin/python -m bench.accuracy \\
        --seq kitti06=/work/shared/data/kitti_odometry/sequences/06:/work/shared/data/kitti_odometry/poses/06.txt \\
        --trained-on kitti01,kitti03 --repeats 3 --keep /tmp/h10/runs --out bench/results/accuracy
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from bench.machine import command_line, describe, write_results
from metricslam.errors import AlignmentError
from metricslam.geometry.align import align_trajectory
from metricslam.trajectory.io import read_kitti_poses, write_kitti_poses

METRICSLAM = [sys.executable, "-m", "metricslam_cli.main"]
#: eval keys summarized over repeats (units in docs/evaluation.md)
METRIC_KEYS = ("t_rel_pct", "r_rel_deg_per_100m", "ate_rmse_m", "ate_rmse_sim3_m", "scale_ratio", "scale_error_pct")
VARIANTS = ("metric", "noscale", "noscale_sim3")
VARIANT_LABEL = {"metric": "metricslam (learned scale, no GT)", "noscale": "--no-scale, as run",
                 "noscale_sim3": "--no-scale + Sim(3) oracle alignment"}


def code_description() -> str:
    """Which ``metricslam`` the child runs use (PYTHONPATH may point at a frozen snapshot) and
    the checkout's commit; set ``METRICSLAM_CODE_NOTE`` to say where a snapshot came from."""
    where = subprocess.run([sys.executable, "-c", "import metricslam; print(metricslam.__file__)"],
                           capture_output=True, text=True).stdout.strip()
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    note = os.environ.get("METRICSLAM_CODE_NOTE", "")
    return f"metricslam imported from {where}; checkout HEAD {head or '?'}" + (f"; {note}" if note else "")


def _run(cmd: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True)


def _shown(cmd: list[str]) -> str:
    return "metricslam " + " ".join(cmd[len(METRICSLAM):])


def run_slam(name: str, seq_dir: str, no_scale: bool, workdir: Path, repeat: int | None = None,
             run_args: tuple[str, ...] = ()) -> dict:
    """One ``metricslam run``; returns paths, command, stats or the error text. ``repeat``
    (1-based) tags the files of repeated runs; ``run_args`` are extra arguments (``--run-args``,
    e.g. ``--deterministic``)."""
    tag = f"{name}_{'noscale' if no_scale else 'metric'}" + (f"_r{repeat}" if repeat else "")
    est, stats = workdir / f"{tag}.txt", workdir / f"{tag}_stats.json"
    cmd = METRICSLAM + ["run", seq_dir, "--out", str(est), "--json", str(stats), "--no-progress", *run_args,
                        *(["--no-scale"] if no_scale else [])]
    proc = _run(cmd)
    out = {"command": _shown(cmd), "est": str(est), "stats_json": str(stats)}
    if proc.returncode != 0:
        out["error"] = (proc.stderr or proc.stdout)[-600:].strip()
    else:  # the per-keyframe scale history stays in the kept stats file (the retired bench/plots.py read it: docs/history/bench_retired.md)
        out["stats"] = {k: v for k, v in json.loads(stats.read_text()).items()
                        if k not in ("scale_history", "scale_corrections")}
    return out


def sim3_aligned(est: Path, gt: Path, out: Path) -> str | None:
    """Write ``est`` Sim(3)-aligned onto ``gt``; returns an error text when not alignable."""
    T_est, T_gt = read_kitti_poses(est), read_kitti_poses(gt)
    try:
        _, T_aligned = align_trajectory(T_est, T_gt[: len(T_est)], with_scale=True)
    except AlignmentError as exc:
        return str(exc)
    write_kitti_poses(out, T_aligned)
    return None


def evaluate(pairs: list[tuple[str, str]], out_json: Path) -> dict:
    """``metricslam eval`` with one or several ``--gt/--est`` pairs; returns its JSON or error."""
    cmd = METRICSLAM + ["eval"]
    for gt, est in pairs:
        cmd += ["--gt", gt, "--est", est]
    cmd += ["--json", str(out_json)]
    proc = _run(cmd)
    if proc.returncode != 0:
        return {"command": _shown(cmd), "error": (proc.stderr or proc.stdout)[-600:].strip()}
    return {"command": _shown(cmd), "result": json.loads(out_json.read_text())}


def _f(x, fmt: str = ".2f") -> str:
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, fmt)


def summarize(results: list[dict]) -> dict:
    """Per metric over repeated runs: ``{key: {"mean", "std", "n", "values"}}`` (``std`` is the
    sample standard deviation, None for one run; runs where the metric is undefined are left
    out)."""
    out = {}
    for key in METRIC_KEYS:
        vals = [float(r[key]) for r in results if isinstance(r.get(key), (int, float)) and np.isfinite(r[key])]
        out[key] = {"mean": float(np.mean(vals)) if vals else None,
                    "std": float(np.std(vals, ddof=1)) if len(vals) > 1 else None, "n": len(vals), "values": vals}
    return out


_FMT = {"scale_ratio": ".3f", "scale_error_pct": ".1f"}


def metric_cells(results: list[dict]) -> str:
    """Table cells: t_rel, r_rel, ATE SE(3), ATE Sim(3), scale ratio, scale error; ``mean ± sd``
    over several runs."""
    if len(results) == 1:
        return " | ".join(_f(results[0].get(k), _FMT.get(k, ".2f")) for k in METRIC_KEYS)
    summary = summarize(results)
    cells = []
    for k in METRIC_KEYS:
        m, fmt = summary[k], _FMT.get(k, ".2f")
        cells.append("—" if m["mean"] is None else
                     _f(m["mean"], fmt) + (f" ± {_f(m['std'], fmt)}" if m["std"] is not None else "")
                     + ("" if m["n"] == len(results) else f" ({m['n']} runs)"))
    return " | ".join(cells)


def _why(ev: dict, fallback: str) -> str:
    why = ev.get("error") or fallback
    return why.splitlines()[-1][:160] if why else "?"


def render_markdown(report: dict) -> str:
    n_rep = report.get("repeats", 1)
    head = ("| t_rel % | r_rel °/100 m | ATE SE(3) m | ATE Sim(3) m | scale ratio | scale err % |")
    lines = ["# Table 1 — accuracy: metricslam vs --no-scale (same run)", "",
             f"Command: ``{report['command']}``  ", f"Machine: {report['machine']}  ",
             f"Code: {report['code']}  ", f"Date: {report['date_utc']}", "",
             "Variants: " + "; ".join(f"**{k}** = {v}" for k, v in VARIANT_LABEL.items()) + ".", ""]
    if n_rep > 1:
        lines += [(f"Every sequence and mode ran **{n_rep} times**; cells are mean ± sd (sample "
                   "standard deviation over the runs; a count in brackets when the metric was "
                   "undefined in some runs). Every run's numbers are in the JSON (`repeats`)."), ""]
    lines += ["## Per sequence", "",
              "| sequence | depth net trained on it? | frames | GT path m | segment lengths m | variant "
              + head, "| --- | --- | --- | --- | --- | --- " + "| --- " * 6 + "|"]
    for s in report["sequences"]:
        for v in VARIANTS:
            evs = [rep["eval"].get(v, {}) for rep in s["repeats"]]
            ok = [ev["result"] for ev in evs if "result" in ev]
            if not ok:
                mode = "noscale" if v.startswith("noscale") else "metric"
                why = _why(evs[0], s["repeats"][0]["runs"].get(mode, {}).get("error", "not run"))
                lines.append(f"| {s['name']} | {s['trained_on']} | — | — | — | {v} | failed: {why} |||||")
                continue
            m = ok[0]
            lens = m.get("t_rel_lengths_m") or []
            lens_txt = f"{lens[0]:.0f}–{lens[-1]:.0f}" if lens else "none fits"
            fails = "" if len(ok) == len(evs) else f" ({len(evs) - len(ok)} of {len(evs)} runs failed)"
            lines.append(f"| {s['name']} | {s['trained_on']} | {m.get('n_frames')} | "
                         f"{_f(m.get('path_length_m'), '.1f')} | {lens_txt} | {v}{fails} | {metric_cells(ok)} |")
    for group, pooled in report["pooled"].items():
        reps = report["pooled_repeats"][group]
        lines += ["", f"## Pooled over {group}: {', '.join(pooled['sequences']) or 'none'}", "",
                  "Pooled = all segments / all frames together (the devkit's average); mean = plain "
                  "mean of the per-sequence numbers" + ("; both computed per repeat, then mean ± sd "
                                                       "over repeats." if n_rep > 1 else "."), "",
                  "| variant | average " + head, "| --- | --- " + "| --- " * 6 + "|"]
        for v in VARIANTS:
            results = [r[v]["result"] for r in reps if "result" in r.get(v, {})]
            if not results:
                ev = pooled.get(v, {})
                lines.append(f"| {v} | failed: {str(ev.get('error', 'no sequences'))[-160:]} |||||||")
                continue
            if "per_sequence" not in results[0]:  # one sequence: the flat result
                lines.append(f"| {v} | (one sequence) | {metric_cells(results)} |")
                continue
            lines.append(f"| {v} | pooled | {metric_cells(results)} |")
            lines.append(f"| {v} | mean of sequences | "
                         f"{metric_cells([r.get('mean_of_sequences', {}) for r in results])} |")
        lines += ["", "Pooled eval commands" + (" (repeat 1; the others alike)" if n_rep > 1 else "") + ":", ""]
        lines += [f"* {v}: `{pooled[v]['command']}`" for v in VARIANTS if v in pooled]
    lines += ["", "## Run commands", ""]
    for s in report["sequences"]:
        for k, rep in enumerate(s["repeats"], 1):
            for r in rep["runs"].values():
                st = r.get("stats", {})
                lines.append(f"* {'' if n_rep == 1 else f'run {k}: '}`{r['command']}` — "
                             f"{_f(st.get('fps'), '.1f')} frames/s, {st.get('keyframes', '—')} keyframes, "
                             f"{st.get('tracking_losses', '—')} tracking losses"
                             + (f", FAILED: {r['error'].splitlines()[-1][:200]}" if "error" in r else ""))
    lines += ["", "## Notes", ""] + [f"* {n}" for n in report["notes"]]
    return "\n".join(lines) + "\n"


def run_sequence(name: str, seq_dir: str, gt: str, workdir: Path, repeat: int | None,
                 run_args: tuple[str, ...] = ()) -> dict:
    """Both modes once, then the three evaluations: ``{"runs", "eval", "aligned_est"?}``."""
    tag = name + (f"_r{repeat}" if repeat else "")
    out: dict = {"runs": {}, "eval": {}}
    for no_scale in (False, True):
        r = run_slam(name, seq_dir, no_scale, workdir, repeat, run_args)
        out["runs"]["noscale" if no_scale else "metric"] = r
        print(f"{tag} {'noscale' if no_scale else 'metric'}: "
              f"{r.get('error', '').splitlines()[-1:] or r['stats'].get('fps')}", flush=True)
    for v in VARIANTS:
        run = out["runs"]["noscale" if v.startswith("noscale") else "metric"]
        if "error" in run:
            out["eval"][v] = {"error": run["error"]}
            continue
        est = Path(run["est"])
        if v == "noscale_sim3":
            est = workdir / f"{tag}_noscale_sim3.txt"
            err = sim3_aligned(Path(run["est"]), Path(gt), est)
            if err:
                out["eval"][v] = {"error": f"Sim(3) alignment undefined: {err}"}
                continue
            out["aligned_est"] = str(est)
        out["eval"][v] = evaluate([(gt, str(est))], workdir / f"{tag}_{v}_eval.json")
    return out


def pool(seqs: list[dict], k: int, tag: str, workdir: Path, n_rep: int) -> dict:
    """Pooled evaluation of repeat ``k`` (0-based) over ``seqs``, per variant."""
    pooled = {"sequences": []}
    for v in VARIANTS:
        ok = [s for s in seqs if "result" in s["repeats"][k]["eval"].get(v, {})]
        pooled["sequences"] = sorted({*pooled["sequences"], *(s["name"] for s in ok)})
        if not ok:
            continue
        pairs = [(s["gt"], s["repeats"][k]["aligned_est"] if v == "noscale_sim3" else
                  s["repeats"][k]["runs"]["noscale" if v == "noscale" else "metric"]["est"]) for s in ok]
        suffix = f"_r{k + 1}" if n_rep > 1 else ""
        pooled[v] = evaluate(pairs, workdir / f"pooled_{tag}_{v}{suffix}_eval.json")
        pooled[v]["sequences"] = [s["name"] for s in ok]
    return pooled


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", action="append", required=True, metavar="NAME=SEQ_DIR:GT.txt",
                   help="sequence folder and its ground-truth KITTI pose file (repeatable)")
    p.add_argument("--trained-on", default="", metavar="NAME,NAME",
                   help="sequences in the depth network's training set (labelled, pooled apart)")
    p.add_argument("--repeats", type=int, default=1, metavar="N",
                   help="run every sequence and mode N times; report mean ± sd (default 1)")
    p.add_argument("--run-args", default="", metavar="ARGS",
                   help="extra arguments for every metricslam run, e.g. --run-args='--deterministic' (then one "
                        "repeat is enough: runs are identical) or '--model FILE.onnx'")
    p.add_argument("--note", action="append", default=[], help="a note line for the report")
    p.add_argument("--keep", required=True, help="folder for estimates, stats and eval JSON")
    p.add_argument("--out", required=True, help="write OUT.md and OUT.json")
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error(f"--repeats must be >= 1, got {args.repeats}")
    n_rep = args.repeats
    run_args = tuple(shlex.split(args.run_args))
    workdir = Path(args.keep)
    workdir.mkdir(parents=True, exist_ok=True)
    trained = {n for n in args.trained_on.split(",") if n}
    report = {"command": command_line("bench.accuracy", argv), "machine": describe(),
              "code": code_description(), "date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
              "repeats": n_rep, "sequences": [], "notes": list(args.note)}
    for spec in args.seq:
        name, rest = spec.split("=", 1)
        seq_dir, gt = rest.rsplit(":", 1)
        s = {"name": name, "seq_dir": seq_dir, "gt": gt, "trained_on": "yes" if name in trained else "no",
             "repeats": [run_sequence(name, seq_dir, gt, workdir, k if n_rep > 1 else None, run_args)
                         for k in range(1, n_rep + 1)]}
        s.update(s["repeats"][0])  # runs / eval / aligned_est of the first run (figures use them)
        s["summary"] = {v: summarize([r["eval"][v]["result"] for r in s["repeats"]
                                      if "result" in r["eval"].get(v, {})]) for v in VARIANTS}
        report["sequences"].append(s)
    groups = {"all sequences": report["sequences"],
              "sequences the depth network never saw": [s for s in report["sequences"] if s["trained_on"] == "no"]}
    report["pooled"], report["pooled_repeats"], report["pooled_summary"] = {}, {}, {}
    for group, seqs in groups.items():
        tag = "all" if group == "all sequences" else "heldout"
        reps = [pool(seqs, k, tag, workdir, n_rep) for k in range(n_rep)]
        report["pooled"][group] = reps[0]
        report["pooled_repeats"][group] = reps
        report["pooled_summary"][group] = {v: summarize([r[v]["result"] for r in reps if "result" in r.get(v, {})])
                                           for v in VARIANTS}
    out = Path(args.out)
    write_results(out, report, render_markdown(report))
    print(f"wrote {out.with_suffix('.md')} and {out.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
