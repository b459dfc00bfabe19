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

Example::

    nice -n 5 .venv/bin/python bench/accuracy.py \\
        --seq kitti06=/work/shared/data/kitti_odometry/sequences/06:/work/shared/data/kitti_odometry/poses/06.txt \\
        --trained-on kitti01,kitti03 --keep /tmp/h10/runs --out bench/results/accuracy
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
from machine import describe
from metricslam.errors import AlignmentError
from metricslam.geometry.align import align_trajectory
from metricslam.trajectory.io import read_kitti_poses, write_kitti_poses

METRICSLAM = [sys.executable, "-m", "metricslam.cli.main"]
VARIANTS = ("metric", "noscale", "noscale_sim3")
VARIANT_LABEL = {
    "metric": "metricslam (learned scale, no GT)",
    "noscale": "--no-scale, as run",
    "noscale_sim3": "--no-scale + Sim(3) oracle alignment",
}


def code_description() -> str:
    """Which ``metricslam`` the child runs use (PYTHONPATH may point at a frozen snapshot) and
    the checkout's commit; set ``METRICSLAM_CODE_NOTE`` to say where a snapshot came from."""
    where = subprocess.run([sys.executable, "-c", "import metricslam; print(metricslam.__file__)"],
                           capture_output=True, text=True).stdout.strip()
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    note = os.environ.get("METRICSLAM_CODE_NOTE", "")
    return f"metricslam imported from {where}; checkout HEAD {head or '?'}" + (f"; {note}" if note else "")


def _run(cmd: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True)


def _shown(cmd: list[str]) -> str:
    return "metricslam " + " ".join(cmd[len(METRICSLAM):])


def run_slam(name: str, seq_dir: str, no_scale: bool, workdir: Path) -> dict:
    """One ``metricslam run``; returns paths, command, stats or the error text."""
    tag = f"{name}_{'noscale' if no_scale else 'metric'}"
    est, stats = workdir / f"{tag}.txt", workdir / f"{tag}_stats.json"
    cmd = METRICSLAM + ["run", seq_dir, "--out", str(est), "--json", str(stats), "--no-progress"]
    if no_scale:
        cmd.append("--no-scale")
    proc = _run(cmd)
    out = {"command": _shown(cmd), "est": str(est)}
    if proc.returncode != 0:
        out["error"] = (proc.stderr or proc.stdout)[-600:].strip()
    else:
        out["stats"] = json.loads(stats.read_text())
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


def metric_cells(m: dict) -> str:
    """Table cells: t_rel, r_rel, ATE SE(3), ATE Sim(3), scale ratio, scale error."""
    return (f"{_f(m.get('t_rel_pct'))} | {_f(m.get('r_rel_deg_per_100m'))} | "
            f"{_f(m.get('ate_rmse_m'))} | {_f(m.get('ate_rmse_sim3_m'))} | "
            f"{_f(m.get('scale_ratio'), '.3f')} | {_f(m.get('scale_error_pct'), '.1f')}")


def write_markdown(report: dict, out_md: Path) -> None:
    head = ("| t_rel % | r_rel °/100 m | ATE SE(3) m | ATE Sim(3) m | scale ratio | scale err % |")
    lines = ["# Table 1 — accuracy: metricslam vs --no-scale (same run)", "",
             f"Command: ``{report['command']}``  ", f"Machine: {report['machine']}  ",
             f"Code: {report['code']}  ", f"Date: {report['date_utc']}", "",
             "Variants: " + "; ".join(f"**{k}** = {v}" for k, v in VARIANT_LABEL.items()) + ".", "",
             "## Per sequence", "",
             "| sequence | depth net trained on it? | frames | GT path m | segment lengths m | variant "
             + head, "| --- | --- | --- | --- | --- | --- " + "| --- " * 6 + "|"]
    for s in report["sequences"]:
        for v in VARIANTS:
            ev = s["eval"].get(v, {})
            if "result" not in ev:
                why = ev.get("error") or s["runs"].get(v.split("_")[0], {}).get("error", "not run")
                lines.append(f"| {s['name']} | {s['trained_on']} | — | — | — | {v} | failed: "
                             f"{why.splitlines()[-1][:160] if why else '?'} |||||")
                continue
            m = ev["result"]
            lens = m.get("t_rel_lengths_m") or []
            lens_txt = f"{lens[0]:.0f}–{lens[-1]:.0f}" if lens else "none fits"
            lines.append(f"| {s['name']} | {s['trained_on']} | {m.get('n_frames')} | "
                         f"{_f(m.get('path_length_m'), '.1f')} | {lens_txt} | {v} | {metric_cells(m)} |")
    for group, pooled in report["pooled"].items():
        lines += ["", f"## Pooled over {group}: {', '.join(pooled['sequences']) or 'none'}", "",
                  "Pooled = all segments / all frames together (the devkit's average); mean = plain "
                  "mean of the per-sequence numbers.", "",
                  "| variant | average " + head, "| --- | --- " + "| --- " * 6 + "|"]
        for v in VARIANTS:
            ev = pooled.get(v, {})
            if "result" not in ev:
                lines.append(f"| {v} | failed: {str(ev.get('error', 'no sequences'))[-160:]} |||||||")
                continue
            r = ev["result"]
            if "per_sequence" not in r:  # one sequence: the flat result
                lines.append(f"| {v} | (one sequence) | {metric_cells(r)} |")
                continue
            lines.append(f"| {v} | pooled | {metric_cells(r)} |")
            lines.append(f"| {v} | mean of sequences | {metric_cells(r.get('mean_of_sequences', {}))} |")
        lines += ["", "Pooled eval commands:", ""]
        lines += [f"* {v}: `{pooled[v]['command']}`" for v in VARIANTS if v in pooled]
    lines += ["", "## Run commands", ""]
    for s in report["sequences"]:
        for mode, r in s["runs"].items():
            st = r.get("stats", {})
            lines.append(f"* `{r['command']}` — {_f(st.get('fps'), '.1f')} frames/s, "
                         f"{st.get('keyframes', '—')} keyframes, "
                         f"{st.get('tracking_losses', '—')} tracking losses"
                         + (f", FAILED: {r['error'].splitlines()[-1][:200]}" if "error" in r else ""))
    lines += ["", "## Notes", ""] + [f"* {n}" for n in report["notes"]]
    out_md.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", action="append", required=True, metavar="NAME=SEQ_DIR:GT.txt",
                   help="sequence folder and its ground-truth KITTI pose file (repeatable)")
    p.add_argument("--trained-on", default="", metavar="NAME,NAME",
                   help="sequences in the depth network's training set (labelled, pooled apart)")
    p.add_argument("--note", action="append", default=[], help="a note line for the report")
    p.add_argument("--keep", required=True, help="folder for estimates, stats and eval JSON")
    p.add_argument("--out", required=True, help="write OUT.md and OUT.json")
    args = p.parse_args(argv)
    workdir = Path(args.keep)
    workdir.mkdir(parents=True, exist_ok=True)
    trained = {n for n in args.trained_on.split(",") if n}
    report = {"command": ".venv/bin/python " + shlex.join(sys.argv), "machine": describe(),
              "code": code_description(), "date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "sequences": [],
              "notes": list(args.note)}
    for spec in args.seq:
        name, rest = spec.split("=", 1)
        seq_dir, gt = rest.rsplit(":", 1)
        s = {"name": name, "seq_dir": seq_dir, "gt": gt,
             "trained_on": "yes" if name in trained else "no", "runs": {}, "eval": {}}
        for no_scale in (False, True):
            r = run_slam(name, seq_dir, no_scale, workdir)
            s["runs"]["noscale" if no_scale else "metric"] = r
            print(f"{name} {'noscale' if no_scale else 'metric'}: "
                  f"{r.get('error', '').splitlines()[-1:] or r['stats'].get('fps')}", flush=True)
        for v in VARIANTS:
            run = s["runs"]["noscale" if v.startswith("noscale") else "metric"]
            if "error" in run:
                s["eval"][v] = {"error": run["error"]}
                continue
            est = Path(run["est"])
            if v == "noscale_sim3":
                est = workdir / f"{name}_noscale_sim3.txt"
                err = sim3_aligned(Path(run["est"]), Path(gt), est)
                if err:
                    s["eval"][v] = {"error": f"Sim(3) alignment undefined: {err}"}
                    continue
                s["aligned_est"] = str(est)
            s["eval"][v] = evaluate([(gt, str(est))], workdir / f"{name}_{v}_eval.json")
        report["sequences"].append(s)
    groups = {"all sequences": report["sequences"],
              "sequences the depth network never saw": [s for s in report["sequences"]
                                                        if s["trained_on"] == "no"]}
    report["pooled"] = {}
    for group, seqs in groups.items():
        pooled = {"sequences": []}
        for v in VARIANTS:
            ok = [s for s in seqs if "result" in s["eval"].get(v, {})]
            pooled["sequences"] = sorted({*pooled["sequences"], *(s["name"] for s in ok)})
            if not ok:
                continue
            pairs = [(s["gt"], s["aligned_est"] if v == "noscale_sim3" else
                      s["runs"]["noscale" if v == "noscale" else "metric"]["est"]) for s in ok]
            tag = "all" if group == "all sequences" else "heldout"
            pooled[v] = evaluate(pairs, workdir / f"pooled_{tag}_{v}_eval.json")
            pooled[v]["sequences"] = [s["name"] for s in ok]
        report["pooled"][group] = pooled
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(report, indent=1, default=str) + "\n")
    write_markdown(report, out.with_suffix(".md"))
    print(f"wrote {out.with_suffix('.md')} and {out.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
