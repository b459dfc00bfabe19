"""Full ``metricslam run`` with learned scale vs ``--no-scale``, evaluated with ``metricslam eval``.

For each sequence folder (KITTI layout: ``image_0/``, ``calib.txt``, ``times.txt``, ground truth
in ``--gt``), runs both variants as separate processes, then the evaluator, and tabulates scale
error (Sim(3) alignment scale), ATE with SE(3) alignment only (% of path length), t_rel, fps
(frames / wall time of the run, depth inference included), keyframes, scale factors and the
loops detected (input frame pairs).

Example::

    .venv/bin/python -m bench.metric_slam \\
        --seq kitti06=/work/shared/data/kitti_odometry/sequences/06:/work/shared/data/kitti_odometry/poses/06.txt \\
        --out bench/results/metric_slam
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.machine import command_line, describe, write_results

METRICSLAM = [sys.executable, "-m", "metricslam_cli.main"]


def end_errors(est_path: Path, gt_path: str) -> dict:
    """End-of-sequence errors after Sim(3) alignment of all positions (metres).

    ``end_err_m``: aligned position error of the last frame; ``gap_err_m``: error of the
    first-to-last displacement (for a sequence that returns to its start, the loop gap).
    """
    import numpy as np
    from metricslam.geometry.align import align_trajectory
    from metricslam.trajectory.io import read_kitti_poses

    est, gt = read_kitti_poses(est_path), read_kitti_poses(gt_path)
    n = min(len(est), len(gt))
    _, al = align_trajectory(est[:n], gt[:n], with_scale=True)
    d_est, d_gt = al[n - 1, :3, 3] - al[0, :3, 3], gt[n - 1, :3, 3] - gt[0, :3, 3]
    return {"end_err_m": float(np.linalg.norm(al[n - 1, :3, 3] - gt[n - 1, :3, 3])),
            "gap_err_m": float(np.linalg.norm(d_est - d_gt))}


def loop_truth(loops: list, gt_path: str, max_dist_m: float = 20.0, max_rot_deg: float = 15.0) -> list[bool]:
    """For each accepted loop (input frame pair), whether ground truth puts the two frames within
    ``max_dist_m`` and ``max_rot_deg`` of each other (a true revisit)."""
    import numpy as np
    from metricslam.geometry import se3, so3
    from metricslam.trajectory.io import read_kitti_poses

    gt = read_kitti_poses(gt_path)
    out = []
    for a, b in loops:
        T = se3.inverse(gt[a]) @ gt[b]
        out.append(bool(np.linalg.norm(T[:3, 3]) < max_dist_m
                        and np.degrees(np.linalg.norm(so3.log(T[:3, :3]))) < max_rot_deg))
    return out


def no_loop_config(workdir: Path, extra: list[str]) -> Path:
    """A ``metricslam run --config`` file that disables loop closure, on top of the user's
    own ``--config`` in ``extra`` if there is one (the ablation: same pipeline otherwise)."""
    import yaml

    base = {}
    if "--config" in extra:
        base = yaml.safe_load(Path(extra[extra.index("--config") + 1]).read_text()) or {}
    graph = base.setdefault("graph", {}) or {}
    graph.setdefault("loop", {})["enabled"] = False
    base["graph"] = graph
    path = workdir / "no_loops.yaml"
    path.write_text(yaml.safe_dump(base))
    return path


def run_one(name: str, seq_dir: str, gt: str, no_scale: bool, workdir: Path, extra: list[str],
            loops: bool = True) -> dict:
    tag = f"{name}_{'noscale' if no_scale else 'scale'}{'' if loops else '_noloops'}"
    est, stats, metrics = workdir / f"{tag}.txt", workdir / f"{tag}_stats.json", workdir / f"{tag}_eval.json"
    if not loops:  # the same `metricslam run` with loop closure switched off by its config
        k = extra.index("--config") if "--config" in extra else None
        rest = extra if k is None else extra[:k] + extra[k + 2:]
        extra = rest + ["--config", str(no_loop_config(workdir, extra))]
    cmd = METRICSLAM + ["run", seq_dir, "--out", str(est), "--json", str(stats)] + extra
    if no_scale:
        cmd.append("--no-scale")
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        return {"name": tag, "error": proc.stderr[-2000:], "command": " ".join(cmd)}
    ev = subprocess.run(METRICSLAM + ["eval", "--gt", gt, "--est", str(est), "--json", str(metrics)],
                        capture_output=True, text=True, check=False)
    if ev.returncode != 0:
        return {"name": tag, "error": ev.stderr[-2000:], "command": " ".join(cmd)}
    m = json.loads(metrics.read_text())
    m = m[0] if isinstance(m, list) else m
    m = m.get("metrics", m) if isinstance(m, dict) else m
    s = json.loads(stats.read_text())
    n = m.get("n_frames") or s.get("frames")
    path = m.get("path_length_m") or float("nan")
    return {
        "name": tag, "command": " ".join(cmd[2:]), "wall_s": wall, "stats": s, "metrics": m,
        "fps_wall": s.get("fps") or (n / wall if n else None),  # run's own frames / s (with depth)
        "ate_pct_of_path": 100.0 * m["ate_rmse_m"] / path if m.get("ate_rmse_m") is not None else None,
        **end_errors(est, gt),
        "loops_true": loop_truth(s.get("backend", s).get("loops", []), gt),
    }


def render(rows: list[dict], commands: list[str], machine: str) -> str:
    """Markdown table of :func:`run_one` rows (also used by ``--render`` on saved JSON)."""
    lines = ["# Metric SLAM: learned scale vs --no-scale", "",
             *(f"Command: `{c if ' -m bench.' in c else '.venv/bin/python ' + c}`  " for c in commands),
             f"Machine: {machine}", "",
             "| run | frames | path m | scale ratio | scale err % | ATE SE(3) m | ATE % path | t_rel % | r_rel °/100 m | end err Sim(3) m | fps | keyframes | scale factors | loops verified / accepted (true) | accepted loops (frames) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['name']} | failed: {r['error'][-200:]!r} |")
            continue
        m, s = r["metrics"], r["stats"]
        back = s.get("backend", s)
        loops = back.get("loops", [])
        lines.append(
            f"| {r['name']} | {m.get('n_frames')} | {m.get('path_length_m', float('nan')):.0f} | "
            f"{m.get('scale_ratio', float('nan')):.3f} | {m.get('scale_error_pct', float('nan')):.1f} | "
            f"{m.get('ate_rmse_m', float('nan')):.2f} | {r['ate_pct_of_path'] or float('nan'):.2f} | "
            f"{m.get('t_rel_pct', float('nan')):.2f} | {m.get('r_rel_deg_per_100m') or float('nan'):.3f} | "
            f"{r['end_err_m']:.2f} | {r['fps_wall'] or float('nan'):.1f} | "
            f"{back.get('keyframes', '?')} | {back.get('scale_factors', '?')} | "
            f"{back.get('loops_verified', '?')} / {len(loops)} ({sum(r.get('loops_true', []))}) | "
            f"{loops[:8]}{' …' if len(loops) > 8 else ''} |")
    return "\n".join(lines) + "\n"


def render_saved(json_paths: list[str], out: Path) -> None:
    """Re-render OUT.md (and a merged OUT.json) from earlier runs' JSON files; fills the
    true/false loop check from the ground truth named in each run's command."""
    rows, commands, machine = [], [], ""
    for jp in json_paths:
        saved = json.loads(Path(jp).read_text())
        commands.append(saved["command"])
        machine = saved["machine"]
        argv = saved["command"].split()
        gts = {a.split("=", 1)[0]: a.rsplit(":", 1)[1] for a in argv if "=" in a and ":" in a}
        for r in saved["rows"]:
            if "error" not in r and "loops_true" not in r:
                gt = next(g for n, g in gts.items() if r["name"].startswith(n + "_"))
                r["loops_true"] = loop_truth(r["stats"].get("backend", r["stats"]).get("loops", []), gt)
            rows.append(r)
    write_results(out, {"rows": rows, "machine": machine, "commands": commands},
                  render(rows, commands, machine))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--render":  # --render A.json [B.json ...] --out OUT
        k = argv.index("--out")
        render_saved(argv[1:k], Path(argv[k + 1]))
        return 0
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", action="append", required=True, metavar="NAME=SEQ_DIR:GT.txt")
    p.add_argument("--out", help="write OUT.md and OUT.json")
    p.add_argument("--keep", help="keep estimates in this folder")
    p.add_argument("--extra", default="", help="extra arguments for metricslam run")
    p.add_argument("--ablate-loops", action="store_true",
                   help="also run each variant with loop closure disabled (rows *_noloops)")
    args = p.parse_args(argv)
    workdir = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="metric_slam_"))
    workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    for spec in args.seq:
        name, rest = spec.split("=", 1)
        seq_dir, gt = rest.rsplit(":", 1)
        for no_scale in (False, True):
            extra = args.extra.split()
            if name.startswith("synth") and "--preset" not in extra:
                extra += ["--preset", "synth"]
            for loops in ((True, False) if args.ablate_loops else (True,)):
                r = run_one(name, seq_dir, gt, no_scale, workdir, extra, loops)
                print(json.dumps({k: v for k, v in r.items() if k != "stats"}, default=str)[:2000], flush=True)
                rows.append(r)
    if args.out:
        machine = describe()
        command = command_line("bench.metric_slam", argv)
        write_results(args.out, {"rows": rows, "machine": machine, "command": command},
                      render(rows, [command], machine))
    return 0


if __name__ == "__main__":
    sys.exit(main())
