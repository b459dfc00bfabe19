"""Lie-group helpers on plain numpy arrays. Conventions: ``docs/conventions.md``."""

from metricslam.geometry import align, se3, sim3, so3

__all__ = ["align", "se3", "sim3", "so3"]
