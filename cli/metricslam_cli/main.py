"""Entry point of the ``metricslam`` command.

Subcommands are listed in :data:`COMMANDS` as ``name -> module``; each module defines
``add_parser(subparsers) -> argparse.ArgumentParser`` that sets ``func(args) -> int`` as default.
Modules must import only argparse-level things at top level so ``metricslam --help`` stays fast.
Every subcommand's parser is a :class:`CommandParser`: its help keeps descriptions as written and
shows each option's default (:class:`HelpFormatter`), whatever formatter the module asked for.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from metricslam import __version__
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
    "map": "metricslam_cli.map_cmd",
}

log = logging.getLogger("metricslam")


def shows_default(action: argparse.Action) -> bool:
    """Whether an option's default says something (not None, False, empty or suppressed)."""
    default = action.default
    return not (default is None or default is False or default is argparse.SUPPRESS
                or (isinstance(default, (list, tuple, str)) and not default))


class HelpFormatter(argparse.HelpFormatter):
    """Each option's help ends with ``(default: …)`` unless it says its default already or has
    none worth showing (:func:`shows_default`)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if text is argparse.SUPPRESS or "default" in text.lower() or not shows_default(action):
            return text
        return f"{text} (default: %(default)s)"


class RawDescriptionHelpFormatter(HelpFormatter, argparse.RawDescriptionHelpFormatter):
    """:class:`HelpFormatter` that keeps the description's lines as written (docstrings)."""


class CommandParser(argparse.ArgumentParser):
    """The parser of every subcommand: a defaults-showing formatter, raw descriptions where the
    command asked for them (``formatter_class=argparse.RawDescriptionHelpFormatter``)."""

    def __init__(self, *args, **kwargs) -> None:
        raw = issubclass(kwargs.get("formatter_class", argparse.HelpFormatter), argparse.RawDescriptionHelpFormatter)
        kwargs["formatter_class"] = RawDescriptionHelpFormatter if raw else HelpFormatter
        super().__init__(*args, **kwargs)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="metricslam",
        description="Metrically-scaled monocular SLAM with learned scale factors.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}",
                        help="print the package version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=CommandParser)
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
