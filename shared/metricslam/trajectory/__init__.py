"""Trajectory files: KITTI (3x4 row-major per line) and TUM (``t tx ty tz qx qy qz qw``).

Conventions: ``docs/conventions.md``.
"""

from metricslam.trajectory.io import (
    read_kitti_poses,
    read_trajectory,
    read_tum,
    write_kitti_poses,
    write_tum,
)

__all__ = ["read_kitti_poses", "read_trajectory", "read_tum", "write_kitti_poses", "write_tum"]
