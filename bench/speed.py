"""Table 3 — speed: per-stage milliseconds, frames/s, CPU time and peak memory of ``metricslam run``.

Runs ``metricslam run SEQ --json STATS`` once per mode (``metric`` = learned scale, ``no-scale``,
``vo-only``) as a child process and reads:

* the run's own ``--json`` statistics: ``ms_per_frame`` / ``ms_per_call`` per stage of the local
  VO (frontend = KLT tracking, pose, keyframe, BA, marginalization, hand-off to the back end) and
  the back end's means (depth inference per request, global Sim(3) solve per update, loop check);
* ``os.wait4`` resource usage of the child: peak resident memory (``ru_maxrss``) and CPU seconds
  (user + system, all threads), which are less disturbed by other jobs than wall time.

Global solve time vs graph size was measured by the retired ``bench/graph_scaling.py``
(``bench/results/graph_scaling.md``; ``docs/history/bench_retired.md``).

Example::

    nice -n 5 .venv/bin/python -m bench.speed --seq /tmp/h10/synth_loop1000 --out bench/results/speed
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

from bench.accuracy import METRICSLAM, code_description
from bench.machine import command_line, describe, write_results

MODES = {"metric": [], "no-scale": ["--no-scale"], "vo-only": ["--vo-only"]}
#: (key in ms_per_frame / ms_per_call, label)
VO_STAGES = (("frontend", "frontend: KLT tracking + frame handling"), ("pose", "pose estimation"),
             ("keyframe", "keyframe creation"), ("ba", "sliding-window BA"), ("ba_wait", "wait for BA"),
             ("marginalization", "marginalization (Schur)"), ("backend_handoff", "hand-off to global graph"),
             ("total", "total VO per frame"))
BACKEND_STAGES = (("depth_ms_mean", "depth inference per request (ms)"),
                  ("solve_ms_mean", "global Sim(3) solve per update, mean (ms)"),
                  ("solve_ms_max", "global Sim(3) solve per update, max (ms)"),
                  ("loop_ms_mean", "loop-closure check per keyframe, mean (ms)"),
                  ("ground_ms_mean", "ground-plane fit per keyframe, mean (ms; scale source ground)"),
                  ("ground_cpu_ms_mean", "ground-plane fit per keyframe, thread CPU (ms)"))


def run_mode(seq: str, mode: str, workdir: Path, max_frames: int | None) -> dict:
    """Run one mode as a child; returns stats plus wall, CPU seconds and peak RSS."""
    stats_path = workdir / f"{mode}_stats.json"
    cmd = (METRICSLAM + ["run", seq, "--out", str(workdir / f"{mode}.txt"), "--json", str(stats_path), "--no-progress"]
           + MODES[mode] + (["--max-frames", str(max_frames)] if max_frames else []))
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    wall_s = time.perf_counter() - t0
    stderr = proc.stderr.read()
    shown = "metricslam " + " ".join(cmd[len(METRICSLAM):])
    if os.waitstatus_to_exitcode(status) != 0:
        return {"mode": mode, "command": shown, "error": stderr[-600:]}
    stats = json.loads(stats_path.read_text())
    # the per-keyframe scale lists belong to the accuracy figures, not the speed table
    stats = {k: v for k, v in stats.items() if k not in ("scale_history", "scale_corrections")}
    return {"mode": mode, "command": shown, "stats": stats, "wall_s": wall_s,
            "cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mib": usage.ru_maxrss / 1024.0}


def _f(x, fmt: str = ".1f") -> str:
    return "—" if x is None else format(x, fmt)


def render_markdown(report: dict) -> str:
    rows = [r for r in report["runs"] if "error" not in r]
    modes = [r["mode"] for r in rows]
    hdr = "| " + " | ".join(modes) + " |"
    sep = "| --- " * (len(modes) + 1) + "|"
    lines = ["# Table 3 — speed of `metricslam run`", "",
             f"Command: ``{report['command']}``  ", f"Machine: {report['machine']}  ",
             f"Code: {report['code']}  ", f"Date: {report['date_utc']}  ", f"Sequence: `{report['seq']}`", "",
             "## Whole run", "", "| | " + hdr[2:], sep]
    lines.append("| frames | " + " | ".join(str(r["stats"].get("frames")) for r in rows) + " |")
    lines.append("| keyframes | " + " | ".join(str(r["stats"].get("keyframes")) for r in rows) + " |")
    lines.append("| wall s (incl. image loading) | " + " | ".join(_f(r["wall_s"]) for r in rows) + " |")
    lines.append("| frames/s, wall | " + " | ".join(_f(r["stats"].get("fps")) for r in rows) + " |")
    lines.append("| CPU s (all threads) | " + " | ".join(_f(r["cpu_s"]) for r in rows) + " |")
    lines.append("| CPU ms per frame | " + " | ".join(
        _f(1000 * r["cpu_s"] / r["stats"]["frames"]) for r in rows) + " |")
    lines.append("| peak RSS MiB | " + " | ".join(_f(r["peak_rss_mib"], ".0f") for r in rows) + " |")
    lines += ["", "## Local VO stages (ms per frame, averaged over all frames / ms per call)", "",
              "| stage | " + hdr[2:], sep]
    for key, label in VO_STAGES:
        cells = []
        for r in rows:
            pf, pc = r["stats"].get("ms_per_frame", {}), r["stats"].get("ms_per_call", {})
            cells.append(f"{_f(pf.get(key), '.2f')} / {_f(pc.get(key), '.2f')}" if key in pf else "—")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", "## Global graph back end (runs beside the VO)", "", "| | " + hdr[2:], sep]
    for key, label in BACKEND_STAGES:
        lines.append(f"| {label} | " + " | ".join(
            _f(r["stats"].get("backend", {}).get(key), ".2f") for r in rows) + " |")
    for key in ("depth_requests", "depth_dropped", "scale_factors", "loops_accepted", "corrections"):
        lines.append(f"| {key.replace('_', ' ')} | " + " | ".join(
            str(r["stats"].get("backend", {}).get(key, "—")) for r in rows) + " |")
    lines += ["", "Per-mode commands:", ""] + [f"* {r['mode']}: `{r['command']}`" for r in report["runs"]]
    lines += [f"* {r['mode']} FAILED: {r['error'][-300:]!r}" for r in report["runs"] if "error" in r]
    lines += ["", "## Notes", "", *[f"* {x}" for x in report["notes"]]]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", required=True, help="sequence folder (e.g. a 1,000-frame metricslam synth)")
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--note", action="append", default=[])
    p.add_argument("--out", required=True, help="write OUT.md and OUT.json")
    args = p.parse_args(argv)
    workdir = Path(tempfile.mkdtemp(prefix="metricslam_speed_"))
    report = {"command": command_line("bench.speed", argv), "seq": args.seq,
              "code": code_description(), "date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "runs": [],
              "notes": list(args.note)}
    load_before = os.getloadavg()
    for mode in args.modes:
        r = run_mode(args.seq, mode, workdir, args.max_frames)
        print(mode, {k: v for k, v in r.items() if k != "stats"}, flush=True)
        report["runs"].append(r)
    report["machine"] = describe()
    report["notes"] += ["Load average (1/5/15 min) before: " + "/".join(f"{x:.1f}" for x in load_before)
        + "; after: see Machine. Wall-clock numbers depend on what else ran on the 2 shared "
        "cores; CPU s per frame is the steadier measure.",
        "ms per frame = stage time summed over the run / frames; ms per call = per invocation "
        "(BA and marginalization run once per keyframe). The back end (depth + global solve) "
        "runs in its own thread, so its time overlaps the VO's."]
    out = Path(args.out)
    write_results(out, report, render_markdown(report))
    print(f"wrote {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
