"""Entry point of the ``metricslam`` command.

Subcommands are listed in :data:`COMMANDS` as ``name -> module``; each module defines
``add_parser(subparsers) -> argparse.ArgumentParser`` that sets ``func(args) -> int`` as default.
Modules must import only argparse-level things at top level so ``metricslam --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from metricslam.errors import MetricSlamError

#: subcommand name -> module path. Add a line when a command lands.
COMMANDS: dict[str, str] = {
    "depth": "metricslam_cli.depth_cmd",
    "train": "metricslam_cli.train_cmd",
    "export": "metricslam_cli.export_cmd",
    "eval": "metricslam_cli.eval_cmd",
    "synth": "metricslam_cli.synth_cmd",
    "depth-service": "metricslam_cli.depth_service_cmd",
    "run": "metricslam_cli.run_cmd",
    "slam-service": "metricslam_cli.slam_service_cmd",
    "up": "metricslam_cli.up_cmd",
    "replay": "metricslam_cli.replay_cmd",
    "poses": "metricslam_cli.poses_cmd",
    "demo": "metricslam_cli.demo_cmd",
    "camera": "metricslam_cli.camera_cmd",
    "quantize": "metricslam_cli.quantize_cmd",
    "calibrate": "metricslam_cli.calibrate_cmd",
}

log = logging.getLogger("metricslam")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="metricslam",
        description="Metrically-scaled monocular SLAM with learned scale factors.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in COMMANDS.values():
        importlib.import_module(module).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except MetricSlamError as exc:
        print(f"metricslam {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
