"""``metricslam demo``: the whole system on a fresh machine, no data needed.

1. generate a synthetic stereo sequence with a loop (``metricslam.synth``; only the left images
   are used, ground truth only by the evaluator);
2. start the local stack (router, depth service, SLAM service) on free loopback ports;
3. replay the sequence over Zenoh while recording the live pose stream;
4. query the final optimized trajectory;
5. evaluate both against ground truth, print the metric table, write a trajectory plot PNG;
6. shut everything down.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from metricslam.errors import ServiceError


@dataclass(frozen=True)
class DemoResult:
    """Paths written and the headline numbers."""

    out_dir: Path
    plot_png: Path
    metrics_json: Path
    live: dict
    optimized: dict
    fps: float
    latency_ms_p50: float | None


def _step(i: int, text: str) -> None:
    print(f"[{i}/6] {text}", flush=True)


def run_demo(out_dir: Path, frames: int = 200, seed: int = 0, rate_hz: float = 10.0,
             use_scale: bool = True, size: tuple[int, int] = (1241, 376), keep_seq: bool = True,
             depth_model: str | None = None) -> DemoResult:
    """Run the demo; ``depth_model`` None: the model for rendered worlds (``RENDERED_MODEL_PATH``:
    the shipped default is trained on real streets only and is not meant for rendered ones)."""
    from metricslam.datasets import open_sequence
    from metricslam.depth import RENDERED_MODEL_PATH, DepthModel
    from metricslam.evaluation.evaluator import evaluate_poses
    from metricslam.evaluation.plots import save_plot
    from metricslam.synth import generate_sequence
    from metricslam.trajectory.io import write_kitti_poses
    from metricslam_slam.supervisor.launcher import Stack, free_port
    from metricslam_slam.tools.client import PoseRecorder, query_trajectory
    from metricslam_slam.tools.recording import poses_in_order
    from metricslam_slam.tools.replay import replay_sequence, wait_for_service
    from metricslam_slam.zenoh_config import open_client

    out_dir.mkdir(parents=True, exist_ok=True)
    seq_dir = out_dir / f"synth_loop_{frames}f_seed{seed}"
    t0 = time.monotonic()
    if (seq_dir / "poses" / "00.txt").is_file():
        _step(1, f"synthetic loop sequence already at {seq_dir}")
    else:
        _step(1, f"generating a synthetic {frames}-frame loop ({size[0]}x{size[1]}) -> {seq_dir}")
        generate_sequence(seq_dir, frames=frames, seed=seed, path="loop", size=size, progress=True)
    seq = open_sequence(seq_dir)
    T_gt = seq.T_world_cam_gt

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    depth_port = free_port()
    _step(2, f"starting the stack: zenoh {endpoint}, depth http://127.0.0.1:{depth_port} "
             f"(logs in {out_dir / 'logs'})")
    (out_dir / "logs").mkdir(exist_ok=True)
    model_path = str(depth_model or RENDERED_MODEL_PATH)
    if use_scale:
        print(f"      depth model: {DepthModel.load(model_path).contract.model_id} ({model_path})", flush=True)
    stack = Stack(endpoint, depth_port=depth_port, use_scale=use_scale, log_dir=str(out_dir / "logs"),
                  depth_model=model_path)
    stack.start(on_ready=lambda c: print(f"      {c.name} ready (pid {c.process.pid})", flush=True))
    try:
        session = open_client(endpoint)
        try:
            wait_for_service(session, 30, endpoint)
            recorder = PoseRecorder(session, "demo")
            _step(3, f"replaying {len(seq)} frames at {rate_hz:g} Hz over Zenoh, recording live poses")
            replay_sequence(session, seq, "demo", rate_hz=rate_hz, max_in_flight=4, progress=True)
            if not recorder.wait_frames(len(seq), timeout_s=120):
                raise ServiceError(f"only {len(recorder.poses)} of {len(seq)} poses arrived; see "
                                   f"{out_dir / 'logs' / 'slam-service.log'}")
            recorder.wait_for(lambda r: r.latest_status() is not None
                              and r.latest_status().frames_processed >= len(seq), 10)
            status = recorder.latest_status()
            _step(4, "querying the optimized trajectory")
            trajectory = query_trajectory(session, "demo", timeout_s=10)
            recorder.close()
        finally:
            session.close()
    finally:
        stack.stop()
    _step(5, "evaluating against ground truth")
    _, T_live = poses_in_order(recorder.poses, None, len(seq))
    _, T_opt = poses_in_order({}, trajectory, len(seq))
    write_kitti_poses(out_dir / "live_poses.txt", T_live)
    write_kitti_poses(out_dir / "optimized_poses.txt", T_opt)
    ev_live = evaluate_poses(T_gt, T_live, name="live poses (as published)")
    ev_opt = evaluate_poses(T_gt, T_opt, name="optimized trajectory (end)")
    plot = save_plot([ev_live, ev_opt], out_dir / "trajectory.png")
    lat = np.array([p.processing_ms for p in recorder.poses.values()])
    result = DemoResult(out_dir, plot, out_dir / "metrics.json",
                        ev_live.result.model_dump(), ev_opt.result.model_dump(),
                        float(status.fps) if status else 0.0,
                        float(np.percentile(lat, 50)) if lat.size else None)
    result.metrics_json.write_text(json.dumps({
        "live": result.live, "optimized": result.optimized, "fps": result.fps,
        "service_latency_ms_p50": result.latency_ms_p50,
        "session_stats": status.session_stats if status else {},
        "frames": len(seq), "seconds_total": time.monotonic() - t0}, indent=2, default=str))
    _step(6, f"done in {time.monotonic() - t0:.0f} s; stack stopped")
    return result


def format_table(result: DemoResult) -> str:
    def f(x, fmt="{:.2f}"):
        return "n/a" if x is None else fmt.format(x)

    rows = [("", "scale err %", "scale ratio", "ATE SE3 m", "ATE Sim3 m", "t_rel %", "path m")]
    for name, r in (("live poses", result.live), ("optimized", result.optimized)):
        rows.append((name, f(r["scale_error_pct"]), f(r["scale_ratio"], "{:.3f}"), f(r["ate_rmse_m"]),
                     f(r["ate_rmse_sim3_m"]), f(r["t_rel_pct"]), f(r["path_length_m"], "{:.1f}")))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(row, widths)) for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    lines.append(f"service: {result.fps:.1f} frames/s, frame-in -> pose-out p50 "
                 f"{f(result.latency_ms_p50, '{:.0f}')} ms")
    return "\n".join(lines)
