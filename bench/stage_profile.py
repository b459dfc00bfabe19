"""Where the CPU goes: py-spy stage profiles of ``metricslam run`` and of the depth service.

For every ``--seq NAME=DIR``: one run without the profiler (wall, frames/s, CPU seconds of the
child from ``os.wait4``, peak RSS), then ``--repeats`` runs under ``py-spy record -t -f raw``
whose samples are sorted into stages by :mod:`bench.stages` (decode, KLT, corner detection,
essential RANSAC, pose, window BA, marginalization, depth network, loop closure, global graph,
...) and summed over the repeats. ``--svg`` also writes py-spy's flame graph of the first
sequence. With ``--depth-frames``: the depth service (``metricslam depth-service``, default
settings) under ``--depth-clients`` keep-alive clients (``bench.depth_service_bench``), py-spy
attached to the server process, once with JSON and once with ``.npy`` answers.

Shares are of py-spy's busy samples (threads running or waiting for a core); "thread ms per
frame" = samples / rate / frames, so on a loaded machine it includes waiting for a core. The
unprofiled run's CPU ms per frame is the absolute number.

Example::

    nice -n 5 .venv/bin/python -m bench.stage_profile \\
        --seq 0013=../shared/data/kitti_raw_stereo/sequences/2011_09_26_drive_0013 \\
        --seq 06=../shared/data/kitti_odometry/sequences/06 \\
        --depth-frames ../shared/data/kitti_odometry/sequences/06/image_0 \\
        --svg bench/results/profile_0013.svg --out bench/results/profile
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.accuracy import METRICSLAM, code_description
from bench.machine import command_line, describe, write_results
from bench.stages import DEPTH_RULES, SLAM_RULES, aggregate, merge, parse_raw

PY_SPY = str(Path(sys.executable).with_name("py-spy"))


def _load() -> str:
    return "/".join(f"{x:.2f}" for x in os.getloadavg())


def _wait(proc: subprocess.Popen) -> tuple[int, float, float, float]:
    """(exit code, wall s, CPU s of the child and its waited-for descendants, peak RSS MiB)."""
    t0 = time.perf_counter()
    _, status, usage = os.wait4(proc.pid, 0)
    return (os.waitstatus_to_exitcode(status), time.perf_counter() - t0, usage.ru_utime + usage.ru_stime,
            usage.ru_maxrss / 1024.0)


def profile_sequence(name: str, seq: str, run_args: list[str], repeats: int, rate: int, workdir: Path,
                     svg: Path | None) -> dict:
    """One plain run and ``repeats`` py-spy runs of ``metricslam run SEQ``; see the module doc."""
    base = METRICSLAM + ["run", seq, "--no-progress", *run_args]
    out = workdir / f"{name}.txt"
    load_before = _load()
    t0 = time.perf_counter()
    proc = subprocess.Popen(base + ["--out", str(out), "--json", str(workdir / f"{name}.json")],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    code, _, cpu_s, rss = _wait(proc)
    wall_s = time.perf_counter() - t0
    summary = proc.stdout.read().strip()
    if code != 0:
        raise SystemExit(f"metricslam run failed on {seq} (exit {code})")
    frames = sum(1 for _ in out.open())
    plain = {"wall_s": wall_s, "cpu_s": cpu_s, "cpu_ms_per_frame": 1e3 * cpu_s / frames,
             "fps_wall_incl_startup": frames / wall_s, "peak_rss_mib": rss, "summary": summary,
             "load_before": load_before, "load_after": _load()}
    tables = []
    for k in range(repeats):
        raw = workdir / f"{name}_{k}.raw"
        cmd = [PY_SPY, "record", "-r", str(rate), "-t", "-f", "raw", "-o", str(raw), "--"] + base + [
            "--out", str(workdir / f"{name}_{k}.txt")]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        tables.append(aggregate(parse_raw(raw.read_text()), SLAM_RULES, rate))
    if svg is not None:
        cmd = [PY_SPY, "record", "-r", str(rate), "-f", "flamegraph", "-o", str(svg), "--"] + base + [
            "--out", str(workdir / f"{name}_svg.txt")]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    table = merge(tables)
    for row in table["stages"]:
        row["thread_ms_per_frame"] = 1e3 * row["thread_s"] / (frames * repeats)
    return {"name": name, "seq": seq, "frames": frames, "command": "metricslam " + " ".join(
        base[len(METRICSLAM):]) + " --out EST.txt", "plain": plain, "profile": table,
        "svg": str(svg) if svg else None}


def thread_cpu_s(pid: int) -> dict[int, float]:
    """User + system CPU seconds of every thread of ``pid`` (Linux ``/proc``), by thread id."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # the thread ended meanwhile
            continue
        out[int(task.name)] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return out


def profile_depth_service(frames_dir: Path, clients: int, requests: int, rate: int, workdir: Path,
                          port: int) -> list[dict]:
    """py-spy on the depth-service process while ``clients`` clients send ``requests`` requests,
    once per answer form (JSON, ``.npy``)."""
    from bench.depth_service_bench import run_level
    from tests.depth_service_process import ServiceProcess

    frames = [p.read_bytes() for p in sorted(frames_dir.glob("*.png"))]
    if not frames:
        raise SystemExit(f"no PNG frames in {frames_dir}")
    out = []
    with ServiceProcess(port, settings={"max_queue": 256, "max_connections": 512}) as service:
        run_level(port, frames, 2, True, 100, service.pid)  # warm-up
        for binary in (False, True):
            raw = workdir / f"depth_{'npy' if binary else 'json'}.raw"
            spy = subprocess.Popen([PY_SPY, "record", "-r", str(rate), "-t", "-f", "raw", "-o", str(raw),
                                    "-p", str(service.pid)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(1.0)  # py-spy attaches
            load_before = _load()
            cpu0 = thread_cpu_s(service.pid)
            r = run_level(port, frames, clients, binary, requests, service.pid)
            cpu1 = thread_cpu_s(service.pid)
            spy.send_signal(signal.SIGINT)
            spy.wait(timeout=60)
            stacks = parse_raw(raw.read_text())
            table = aggregate(stacks, DEPTH_RULES, rate)
            names = {s.tid: s.thread for s in stacks}
            per_thread: dict[str, float] = {}
            for tid, c in cpu1.items():
                name = names.get(tid, "native threads (no Python frames)")
                per_thread[name] = per_thread.get(name, 0.0) + 1e3 * (c - cpu0.get(tid, 0.0)) / r.requests
            table["thread_cpu_ms_per_request"] = per_thread
            for row in table["stages"]:
                row["thread_ms_per_request"] = 1e3 * row["thread_s"] / r.requests
            out.append({"form": r.form, "clients": clients, "requests": r.requests, "rps_under_py_spy": r.rps,
                        "server_cpu_ms_per_req": 1e3 * r.server_cpu_s / r.requests,
                        "client_cpu_ms_per_req": 1e3 * r.client_cpu_s / r.requests,
                        "statuses": r.statuses, "load_before": load_before, "load_after": _load(),
                        "profile": table})
    return out


def _stage_rows(table: dict, per_key: str) -> list[str]:
    rows = []
    for r in table["stages"]:
        leaves = "; ".join(f"`{leaf}` {100 * c / max(r['samples'], 1):.0f} %" for leaf, c in r["top_leaves"][:3])
        threads = ", ".join(f"{t} {n}" for t, n in r["threads"].items())
        rows.append(f"| {r['stage']} | {r['share_pct']:.1f} % | {r[per_key]:.2f} | {r['samples']} | {threads} | {leaves} |")
    return rows


def render_markdown(report: dict) -> str:
    lines = [f"# {report['title']}", "", f"Command: ``{report['command']}``  ", f"Machine: {report['machine']}  ",
             f"Code: {report['code']}  ", f"Date: {report['date_utc']}", ""]
    lines += [f"* {x}" for x in report["notes"]]
    for s in report["sequences"]:
        p, t = s["plain"], s["profile"]
        lines += ["", f"## `metricslam run` on {s['name']} ({s['frames']} frames)", "",
                  f"Run: `{s['command']}`. Without the profiler: {p['summary']!r}; CPU {p['cpu_ms_per_frame']:.1f} ms "
                  f"per frame (all threads, start-up included), wall {p['wall_s']:.1f} s incl. start-up, peak RSS "
                  f"{p['peak_rss_mib']:.0f} MiB; load average {p['load_before']} before, {p['load_after']} after.", "",
                  f"Profile: {t.get('runs', 1)} run(s) under py-spy at {t['rate_hz']} Hz, {t['busy_samples']} busy "
                  f"samples ({t['idle_samples']} in blocking waits left out). Threads: "
                  + ", ".join(f"{k} {100 * v / max(t['busy_samples'], 1):.0f} %" for k, v in t["threads"].items())
                  + (f". Flame graph: `{s['svg']}`." if s.get("svg") else "."), "",
                  "| stage | share | thread ms / frame | samples | threads (samples) | innermost frames |",
                  "| --- | ---: | ---: | ---: | --- | --- |", *_stage_rows(t, "thread_ms_per_frame")]
    for d in report.get("depth_service", []):
        t = d["profile"]
        lines += ["", f"## Depth service, {d['clients']} clients, {d['form']} answers ({d['requests']} requests)", "",
                  f"{d['rps_under_py_spy']:.1f} req/s while profiled; server CPU {d['server_cpu_ms_per_req']:.2f} ms per "
                  f"request, client {d['client_cpu_ms_per_req']:.2f} ms; statuses {d['statuses']}; load average "
                  f"{d['load_before']} before, {d['load_after']} after. {t['busy_samples']} busy samples at "
                  f"{t['rate_hz']} Hz. Server CPU ms per request by thread (from /proc, not sampled): "
                  + ", ".join(f"{k} {v:.2f}" for k, v in t["thread_cpu_ms_per_request"].items()) + ".", "",
                  "| stage | share | thread ms / request | samples | threads (samples) | innermost frames |",
                  "| --- | ---: | ---: | ---: | --- | --- |", *_stage_rows(t, "thread_ms_per_request")]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seq", action="append", default=[], metavar="NAME=DIR", help="sequence to run (repeatable)")
    p.add_argument("--run-args", default="", help="extra `metricslam run` arguments, e.g. '--deterministic'")
    p.add_argument("--repeats", type=int, default=2, help="profiled runs per sequence (samples are summed)")
    p.add_argument("--rate", type=int, default=200, help="py-spy samples per second")
    p.add_argument("--svg", type=Path, default=None, help="py-spy flame graph of the first sequence")
    p.add_argument("--depth-frames", type=Path, default=None, help="KITTI image_0 folder: profile the depth service")
    p.add_argument("--depth-clients", type=int, default=4)
    p.add_argument("--depth-requests", type=int, default=1000)
    p.add_argument("--port", type=int, default=18131)
    p.add_argument("--title", default="Where the CPU goes (py-spy stage profile)")
    p.add_argument("--note", action="append", default=[])
    p.add_argument("--keep", type=Path, default=None, help="keep raw py-spy files and outputs here")
    p.add_argument("--out", required=True, help="write OUT.json and OUT.md")
    args = p.parse_args(argv)
    if not Path(PY_SPY).exists() and shutil.which("py-spy") is None:
        raise SystemExit("py-spy is not installed in the venv (pip install py-spy)")
    workdir = args.keep or Path(tempfile.mkdtemp(prefix="metricslam_profile_"))
    workdir.mkdir(parents=True, exist_ok=True)
    report = {"title": args.title, "command": command_line("bench.stage_profile", argv), "code": code_description(),
              "date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "load_before": _load(),
              "notes": list(args.note), "sequences": [], "depth_service": []}
    for k, spec in enumerate(args.seq):
        name, _, seq = spec.partition("=")
        s = profile_sequence(name, seq, args.run_args.split(), args.repeats, args.rate, workdir,
                             args.svg if k == 0 else None)
        print(name, s["plain"]["summary"], f"CPU {s['plain']['cpu_ms_per_frame']:.1f} ms/frame", flush=True)
        report["sequences"].append(s)
    if args.depth_frames is not None:
        report["depth_service"] = profile_depth_service(args.depth_frames, args.depth_clients, args.depth_requests,
                                                        args.rate, workdir, args.port)
    report["machine"] = describe()
    report["notes"].append(
        "py-spy samples threads that run or wait for a core: on this shared 2-core machine a stage's "
        "thread ms include time waiting for a core (pessimistic); compare shares, and the unprofiled CPU ms.")
    report["notes"].append(f"Load average (1/5/15 min) at the start: {report['load_before']}; at the end: see Machine.")
    write_results(args.out, report, render_markdown(report))
    print(f"wrote {Path(args.out).with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
