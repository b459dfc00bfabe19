"""Global Sim(3) graph solve time vs number of keyframes (100 / 1,000 / 10,000).

Drives the real ``GlobalBackend`` (inline, no loop detector) with a synthetic drifting VO that
applies the back end's corrections (``metricslam.slam.graph.synthetic``): per keyframe the
depth map is sampled at 60 landmarks, scale factors and the odometry factor are added, ISAM2
updates and the correction is computed. Reports that per-keyframe time over the first and the
last 10 % of keyframes (what the back end pays per keyframe at that size), the solve after a
loop closure from the newest keyframe to the first one (the worst case: the whole chain is
re-eliminated), a full estimate read-out, and one batch Levenberg-Marquardt solve of the same
graph for comparison (skipped above ``--batch-max`` keyframes).

Example::

    .venv/bin/python -m bench.graph_scaling --sizes 100 1000 10000 --out bench/results/graph_scaling
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import gtsam
import numpy as np

from bench.machine import command_line, describe, write_results
from metricslam.geometry import sim3
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.backend import GlobalBackend
from metricslam.slam.graph.synthetic import SimulatedVO, SyntheticDepthSource, circle_path


def run_size(n: int, cfg: GraphConfig, batch_max: int, seed: int = 0) -> dict:
    T = circle_path(n, 100.0, turns=max(1.0, n / 600.0) * (n - 1) / n)
    vo = SimulatedVO(T, drift_per_kf=0.01, drift_noise=0.003, seed=seed)
    backend = GlobalBackend(cfg.model_copy(update={"inline": True}), depth_source=SyntheticDepthSource(n))
    graph = backend.graph
    update_ms, update_cpu_ms = [], []
    for _ in range(n):
        kf = vo.next_keyframe()  # (synthetic keyframe generation is not timed)
        t0, c0 = time.perf_counter(), time.process_time()
        backend.on_keyframe_marginalized(kf)
        S = backend.take_correction()
        update_ms.append(1e3 * (time.perf_counter() - t0))
        update_cpu_ms.append(1e3 * (time.process_time() - c0))
        if S is not None:
            vo.apply_similarity(S)
    S_true = [sim3.from_se3(T[k], vo.sigma_at_kf[k]) for k in range(n)]
    tail = np.array(update_ms[-max(1, n // 10):])
    tail_cpu = np.array(update_cpu_ms[-max(1, n // 10):])
    t0 = time.perf_counter()
    est = graph.estimates()
    estimate_ms = 1e3 * (time.perf_counter() - t0)
    s_err = np.array([sim3.scale(est[k]) / sim3.scale(S_true[k]) - 1 for k in range(n)])
    S_loop = sim3.inverse(S_true[0]) @ S_true[-1]
    sig = np.array([0.01] * 3 + [max(0.05 * np.linalg.norm(S_loop[:3, 3]), 0.05)] * 3 + [0.05])
    t0 = time.perf_counter()
    decision = graph.add_loop(0, n - 1, S_loop, sig)
    gate_ms = 1e3 * (time.perf_counter() - t0)
    t0 = time.perf_counter()
    graph.solve()
    loop_ms = 1e3 * (time.perf_counter() - t0)
    est_after = graph.estimates()
    end_err_after = float(np.linalg.norm(est_after[n - 1][:3, 3] - T[n - 1][:3, 3]))
    end_err_before = float(np.linalg.norm(est[n - 1][:3, 3] - T[n - 1][:3, 3]))
    batch_ms = None
    if n <= batch_max:
        g = graph.factor_graph()
        values = graph.values()
        t0 = time.perf_counter()
        gtsam.LevenbergMarquardtOptimizer(g, values, gtsam.LevenbergMarquardtParams()).optimize()
        batch_ms = 1e3 * (time.perf_counter() - t0)
    return {
        "keyframes": n,
        "factors": int(graph.factor_graph().size()),
        "update_ms_mean_last10pct": float(tail.mean()),
        "update_ms_p95_last10pct": float(np.percentile(tail, 95)),
        "update_cpu_ms_mean_last10pct": float(tail_cpu.mean()),
        "update_ms_mean_first10pct": float(np.mean(update_ms[: max(1, n // 10)])),
        "loop_gate_ms": gate_ms,
        "estimate_all_ms": estimate_ms,
        "loop_solve_ms": loop_ms,
        "loop_accepted": bool(decision.accepted),
        "end_error_m_before_loop": end_err_before,
        "end_error_m_after_loop": end_err_after,
        "batch_lm_ms": batch_ms,
        "scale_error_pct_max": float(100 * np.abs(s_err).max()),
        "total_build_s": float(sum(update_ms) / 1e3),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[100, 1000, 10000])
    p.add_argument("--batch-max", type=int, default=1000)
    p.add_argument("--mode", default="per_keyframe", choices=("per_keyframe", "per_landmark"))
    p.add_argument("--out", help="write OUT.md and OUT.json")
    args = p.parse_args(argv)
    cfg = GraphConfig(scale_factor_mode=args.mode)
    rows = []
    for n in args.sizes:
        r = run_size(n, cfg, args.batch_max)
        print(json.dumps(r), flush=True)
        rows.append(r)
    if args.out:
        machine = describe()
        lines = [
            "# Global graph solve time vs keyframes", "",
            f"Command: `{command_line('bench.graph_scaling', argv)}`  ", f"Machine: {machine}", "",
            f"Each keyframe: 1 odometry factor + {cfg.max_scale_landmarks} landmark scale measurements "
            f"(scale_factor_mode={cfg.scale_factor_mode}), one ISAM2 update (relinearize every "
            f"{cfg.relinearize_skip}). Update = everything the back end does per keyframe in the graph.",
            "", "| keyframes | factors | update ms, first 10 % | update ms, last 10 % (wall) | p95 | CPU ms | all estimates ms | loop gate ms | loop solve ms | end error m before → after loop | batch LM ms | max scale err % |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for r in rows:
            b = "—" if r["batch_lm_ms"] is None else f"{r['batch_lm_ms']:.0f}"
            lines.append(f"| {r['keyframes']} | {r['factors']} | {r['update_ms_mean_first10pct']:.2f} | "
                         f"{r['update_ms_mean_last10pct']:.2f} | {r['update_ms_p95_last10pct']:.2f} | "
                         f"{r['update_cpu_ms_mean_last10pct']:.2f} | {r['estimate_all_ms']:.1f} | "
                         f"{r['loop_gate_ms']:.0f} | {r['loop_solve_ms']:.0f} | "
                         f"{r['end_error_m_before_loop']:.1f} → {r['end_error_m_after_loop']:.2f} | {b} | "
                         f"{r['scale_error_pct_max']:.1f} |")
        write_results(args.out, {"rows": rows, "machine": machine, "command": command_line("bench.graph_scaling", argv)},
                      "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
