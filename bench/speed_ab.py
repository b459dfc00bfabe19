"""Before/after speed of ``metricslam run`` on the same machine, interleaved, with an accuracy check.

Each ``--variant NAME=PYTHONPATH`` is a copy of the code (e.g. a frozen snapshot of the code
before a change, and the working tree ``shared``). Every round runs every sequence once per
variant, alternating, so slow spells of a shared machine hit all variants alike; each run
records frames/s (the run's own, start-up excluded), wall seconds including start-up, CPU
seconds of the child (``os.wait4``: all threads) and the load average before it. Then, per
variant, one ``metricslam run --deterministic`` per sequence: the trajectory's bytes (SHA-256,
compared with the first variant's) and, with ground truth, ``metricslam eval`` (scale ratio, ATE)
and the relative change against the first variant.

Example::

    nice -n 5 .venv/bin/python -m bench.speed_ab --variant before=/tmp/base --variant after=shared \\
        --seq 0013=../shared/data/kitti_raw_stereo/sequences/2011_09_26_drive_0013:\\
../shared/data/kitti_raw_stereo/poses/2011_09_26_drive_0013.txt \\
        --seq 06=../shared/data/kitti_odometry/sequences/06:../shared/data/kitti_odometry/poses/06.txt \\
        --rounds 3 --out bench/results/speed_ab
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.accuracy import METRICSLAM
from bench.machine import command_line, describe, write_results


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def _env(pythonpath: str, variables: dict[str, str] | None = None) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(pythonpath).resolve())
    env.update(variables or {})
    return env


def timed_run(pythonpath: str, seq: str, out: Path, extra: list[str],
              variables: dict[str, str] | None = None) -> dict:
    """One ``metricslam run``; frames/s from its ``--json``, CPU from ``os.wait4``."""
    stats = out.with_suffix(".json")
    cmd = METRICSLAM + ["run", seq, "--no-progress", "--out", str(out), "--json", str(stats), *extra]
    load = _load()
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=_env(pythonpath, variables), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"metricslam run failed: PYTHONPATH={pythonpath} {' '.join(cmd)}")
    s = json.loads(stats.read_text())
    return {"fps": s["fps"], "frames": s["frames"], "keyframes": s["keyframes"], "wall_s_incl_startup": wall,
            "cpu_s": usage.ru_utime + usage.ru_stime,
            "cpu_ms_per_frame": 1e3 * (usage.ru_utime + usage.ru_stime) / s["frames"], "load_before": load}


def evaluate(pythonpath: str, gt: str, est: Path) -> dict:
    out = est.with_suffix(".eval.json")
    subprocess.run(METRICSLAM + ["eval", "--gt", gt, "--est", str(est), "--json", str(out)], env=_env(pythonpath),
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    d = json.loads(out.read_text())
    return {k: d[k] for k in ("scale_ratio", "scale_error_pct", "ate_rmse_m", "ate_rmse_sim3_m", "t_rel_pct")}


def _median(rows: list[dict], key: str) -> float:
    return float(statistics.median(r[key] for r in rows))


def render_markdown(report: dict) -> str:
    names = [v["name"] for v in report["variants"]]
    lines = ["# `metricslam run` before / after, interleaved", "", f"Command: ``{report['command']}``  ",
             f"Machine: {report['machine']}  ", f"Date: {report['date_utc']}  ",
             "Variants: " + ", ".join(f"`{v['name']}` = PYTHONPATH `{v['pythonpath']}`"
                                      + "".join(f" `{k}={x}`" for k, x in v.get("env", {}).items())
                                      for v in report["variants"]),
             "", *[f"* {x}" for x in report["notes"]], "", "## Speed (median over rounds)", "",
             "| sequence | variant | runs | frames/s (run's own) | min–max | CPU ms / frame | wall s incl. start-up "
             "| load before each run (1 min) |", "| --- | --- | ---: | ---: | --- | ---: | ---: | --- |"]
    for seq, per in report["speed"].items():
        for name in names:
            rows = per[name]
            fps = [r["fps"] for r in rows]
            lines.append(f"| {seq} | {name} | {len(rows)} | {_median(rows, 'fps'):.1f} | {min(fps):.1f}–{max(fps):.1f} | "
                         f"{_median(rows, 'cpu_ms_per_frame'):.1f} | {_median(rows, 'wall_s_incl_startup'):.2f} | "
                         + ", ".join(f"{r['load_before'][0]:.2f}" for r in rows) + " |")
    lines += ["", "## Accuracy (`--deterministic`, one run per variant)", "",
              "| sequence | variant | trajectory SHA-256 (12) | byte-identical to first | scale ratio | scale Δ % | "
              "ATE m | ATE Δ % |", "| --- | --- | --- | --- | ---: | ---: | ---: | ---: |"]
    for seq, per in report["accuracy"].items():
        for name in names:
            a = per[name]
            ev = a.get("eval") or {}
            lines.append(f"| {seq} | {name} | `{a['sha256'][:12]}` | {'yes' if a['identical_to_first'] else 'NO'} | "
                         f"{ev.get('scale_ratio', float('nan')):.6f} | {a.get('scale_change_pct', 0.0):+.4f} | "
                         f"{ev.get('ate_rmse_m', float('nan')):.4f} | {a.get('ate_change_pct', 0.0):+.4f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--variant", action="append", required=True, metavar="NAME=PYTHONPATH")
    p.add_argument("--variant-env", action="append", default=[], metavar="NAME=VAR=VALUE",
                   help="an environment variable for one variant's runs (e.g. a config switch the other lacks)")
    p.add_argument("--seq", action="append", required=True, metavar="NAME=DIR[:GT_POSES]")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--run-args", default="", help="extra `metricslam run` arguments for the timed runs")
    p.add_argument("--no-accuracy", action="store_true", help="skip the --deterministic runs")
    p.add_argument("--note", action="append", default=[])
    p.add_argument("--out", required=True, help="write OUT.json and OUT.md")
    args = p.parse_args(argv)
    variants = [dict(zip(("name", "pythonpath"), v.split("=", 1))) for v in args.variant]
    for spec in args.variant_env:
        name, var, value = spec.split("=", 2)
        next(v for v in variants if v["name"] == name).setdefault("env", {})[var] = value
    seqs = []
    for spec in args.seq:
        name, _, rest = spec.partition("=")
        path, _, gt = rest.partition(":")
        seqs.append((name, path, gt or None))
    work = Path(tempfile.mkdtemp(prefix="metricslam_speed_ab_"))
    report = {"command": command_line("bench.speed_ab", argv), "variants": variants,
              "date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "load_at_start": _load(),
              "notes": list(args.note), "speed": {}, "accuracy": {}}
    for r in range(args.rounds):
        for name, path, _ in seqs:
            order = variants if r % 2 == 0 else variants[::-1]  # alternate who goes first
            for v in order:
                row = timed_run(v["pythonpath"], path, work / f"{name}_{v['name']}_{r}.txt", args.run_args.split(),
                                v.get("env"))
                report["speed"].setdefault(name, {}).setdefault(v["name"], []).append(row)
                print(f"round {r} {name} {v['name']}: {row['fps']:.1f} frames/s, {row['cpu_ms_per_frame']:.1f} "
                      f"CPU ms/frame, load {row['load_before'][0]:.2f}", flush=True)
    if not args.no_accuracy:
        for name, path, gt in seqs:
            first = None
            for v in variants:
                est = work / f"{name}_{v['name']}_det.txt"
                timed_run(v["pythonpath"], path, est, ["--deterministic"], v.get("env"))
                a = {"sha256": hashlib.sha256(est.read_bytes()).hexdigest(), "trajectory": str(est)}
                if gt:
                    a["eval"] = evaluate(v["pythonpath"], gt, est)
                first = first or a
                a["identical_to_first"] = a["sha256"] == first["sha256"]
                if gt:
                    a["scale_change_pct"] = 100 * (a["eval"]["scale_ratio"] / first["eval"]["scale_ratio"] - 1)
                    a["ate_change_pct"] = 100 * (a["eval"]["ate_rmse_m"] / first["eval"]["ate_rmse_m"] - 1)
                report["accuracy"].setdefault(name, {})[v["name"]] = a
                print(name, v["name"], a["sha256"][:12], a.get("eval"), flush=True)
    report["machine"] = describe()
    report["notes"].append(
        "frames/s is the run's own figure (frame loop incl. image loading, start-up excluded); CPU ms per "
        "frame covers the whole process (all threads, start-up included). The machine is shared: the "
        "1-min load average before every run is listed; above 0, wall numbers are pessimistic.")
    write_results(args.out, report, render_markdown(report))
    print(f"wrote {Path(args.out).with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
