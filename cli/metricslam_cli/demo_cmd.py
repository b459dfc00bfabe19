"""``metricslam demo`` (what ``make demo`` runs): synthetic loop -> live stack -> metrics + plot.

Needs no data and no network: generates a synthetic sequence with a loop, starts the router,
depth and SLAM services, replays the sequence over Zenoh, records the live poses, evaluates them
against the ground truth, prints the metric table and writes ``trajectory.png``.
"""

from __future__ import annotations

import argparse

from metricslam_cli.extras import require


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo", help="end-to-end demo on a generated sequence (no data needed)",
        description="Generates a synthetic loop, runs the whole stack over Zenoh on loopback, "
        "evaluates the live poses against ground truth, prints the metric table and writes a "
        "trajectory plot.")
    p.add_argument("--out-dir", default=None, metavar="DIR",
                   help="where the sequence, poses, metrics.json and trajectory.png go "
                   "(default: <tmp>/metricslam-demo)")
    p.add_argument("--frames", type=int, default=200, help="sequence length (10 Hz)")
    p.add_argument("--seed", type=int, default=0, help="seed of the generated world and path")
    p.add_argument("--rate", type=float, default=10.0, metavar="HZ", help="replay rate")
    p.add_argument("--no-scale", action="store_true", help="baseline without learned scale")
    p.add_argument("--model", default=None, metavar="PATH",
                   help="depth model (default: the shipped model for rendered worlds, "
                   "depth_l3_rendered_int8.onnx; the default for real cameras, depth_l3_int8.onnx, "
                   "is trained on real streets only)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    require(*(() if args.no_scale else ("depth-service",)), "slam-service", "synth", "plots", command="demo")

    import tempfile
    from pathlib import Path

    from metricslam.errors import ConfigError
    from metricslam_slam.demo import format_table, run_demo

    if args.frames < 30:
        raise ConfigError(f"--frames must be >= 30 for a meaningful loop, got {args.frames}")
    out_dir = Path(args.out_dir) if args.out_dir else Path(tempfile.gettempdir()) / "metricslam-demo"
    result = run_demo(out_dir, frames=args.frames, seed=args.seed, rate_hz=args.rate,
                      use_scale=not args.no_scale, depth_model=args.model)
    print()
    print(format_table(result))
    print(f"\nplot:    {result.plot_png}\nmetrics: {result.metrics_json}")
    return 0
