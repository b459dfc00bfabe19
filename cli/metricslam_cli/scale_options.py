"""``--scale-sources`` and ``--mount-height``: the scale sources of a SLAM run or service.

Shared by ``run``, ``up``, ``slam-service`` and ``camera`` so their spelling and checks agree;
the values land in the ``scale`` section of the :class:`~metricslam.slam.system_config.SystemConfig`
(docs/ground_scale.md).
"""

from __future__ import annotations

import argparse
import logging


def add_scale_options(p: argparse.ArgumentParser, note: str = "") -> None:
    """Add ``--scale-sources`` and ``--mount-height`` to a command's parser (``note``: appended
    to both helps, e.g. who owns the settings)."""
    p.add_argument("--scale-sources", default=None, metavar="LIST",
                   help="comma-separated scale sources of the global graph: learned (the depth "
                        "network, default), ground (the road plane and --mount-height) or "
                        "learned,ground (docs/ground_scale.md)" + note)
    p.add_argument("--mount-height", type=float, default=None, metavar="M",
                   help="camera optical centre above the road in metres (0 < M <= 10; KITTI: 1.65), "
                        "for ground-plane scale; default: the calibration file's mount_height_m" + note)


def scale_flags(args: argparse.Namespace, calibration_mount_height_m: float | None = None) -> tuple[dict, dict]:
    """``(profile, overrides)`` layers for :func:`~metricslam.slam.config_file.load_system_config`:
    the calibration file's mounting height and the flags as overrides (``--mount-height`` wins).

    Raises:
        ConfigError: a bad ``--scale-sources`` list or ``--mount-height``.
    """
    from metricslam.slam.ground.config import check_mount_height, parse_scale_sources

    profile: dict = {}
    overrides: dict = {}
    if calibration_mount_height_m is not None:
        # docs/ground_scale.md: --mount-height, else the calibration file, else the config file;
        # and the command line is one layer, so ``--scale-sources ground`` sees this height
        overrides["mount_height_m"] = float(calibration_mount_height_m)
    mount_height = getattr(args, "mount_height", None)
    sources = getattr(args, "scale_sources", None)
    if mount_height is not None:
        overrides["mount_height_m"] = check_mount_height(mount_height, "--mount-height")
    if sources is not None:
        overrides["sources"] = list(parse_scale_sources(sources))
    return ({"scale": profile} if profile else {}), ({"scale": overrides} if overrides else {})


def log_scale_sources(config: object, log: logging.Logger) -> None:
    """One info line on the scale sources (and a missing mounting height)."""
    scale = config.scale
    if scale.mount_height_m is None:
        log.info("no camera mounting height (--mount-height, mount_height_m): learned scale only")
    else:
        log.info("scale sources %s, camera %.3f m above the road", ",".join(scale.sources), scale.mount_height_m)
