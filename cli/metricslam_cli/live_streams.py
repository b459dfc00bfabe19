"""``metricslam run --live-out / --continuous-out``: every frame's live pose (what the SLAM service
publishes on ``…/pose``) and its continuous odometry pose (``…/odom``,
:mod:`metricslam.trajectory.continuous`), collected beside the run and written at its end.

The continuous stream is an observer (it subscribes to the back end's warp events): the run's
optimized trajectory (``--out``) is byte-identical with or without it (``bench/pose_jumps.py``
checks it).
"""

from __future__ import annotations

import numpy as np

from metricslam.slam.types import PoseEstimate
from metricslam.trajectory.continuous import ContinuousOdometry, ContinuousOdometryConfig
from metricslam.trajectory.io import write_kitti_poses, write_tum


class LiveStreams:
    """Collects the two streams of one run.

    Args:
        session: the run's session (its ``backend.events`` feed the continuous stream).
        horizon_s: :attr:`ContinuousOdometryConfig.horizon_s` (None: its default).
    """

    def __init__(self, session, horizon_s: float | None = None) -> None:
        config = ContinuousOdometryConfig() if horizon_s is None else ContinuousOdometryConfig(horizon_s=horizon_s)
        self.odometry = ContinuousOdometry(config)
        self.odometry.attach(session)
        self.t_ns: list[int] = []
        self.live: list[np.ndarray] = []
        self.continuous: list[np.ndarray] = []

    def after_frame(self, est: PoseEstimate) -> None:
        """Record frame ``est`` (call right after ``process`` returned it)."""
        self.t_ns.append(int(est.t_ns))
        self.live.append(np.asarray(est.T_world_cam, dtype=np.float64))
        self.continuous.append(self.odometry.update(est).T_world_cam)

    def write(self, live_path: str | None, continuous_path: str | None, fmt: str = "kitti") -> None:
        """Write the streams given a path: one pose per processed frame, KITTI or TUM (``fmt``)."""
        t_ns = np.array(self.t_ns, dtype=np.int64)
        for path, poses in ((live_path, self.live), (continuous_path, self.continuous)):
            if not path:
                continue
            T = np.array(poses, dtype=np.float64).reshape(-1, 4, 4)
            if fmt == "tum":
                write_tum(path, t_ns, T)
            else:
                write_kitti_poses(path, T)

    def stats(self) -> dict:
        """For the run's ``--json``: the horizon and how many corrections were blended."""
        return {"horizon_s": self.odometry.config.horizon_s, "corrections": self.odometry.corrections,
                "reanchors": self.odometry.reanchors}
