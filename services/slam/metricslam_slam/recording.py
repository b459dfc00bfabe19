"""Turn recorded pose messages into a trajectory file (KITTI or TUM), one line per frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from metricslam.errors import ServiceError
from metricslam.trajectory.io import write_kitti_poses, write_tum
from metricslam.wire.codec import PoseMessage, TrajectoryMessage


def poses_in_order(poses: dict[int, PoseMessage], trajectory: TrajectoryMessage | None,
                   n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """``(t_ns (N,), T_world_cam (N, 4, 4))`` of frames ``0..n_frames-1`` in frame order, from
    ``trajectory`` if given else from the live ``poses``.

    Raises:
        ServiceError: a frame has no pose (names the first missing ones).
    """
    if trajectory is not None:
        source = {int(i): (int(t), T) for i, t, T in
                  zip(trajectory.frame_index, trajectory.t_ns, trajectory.T_world_cam)}
    else:
        source = {i: (p.t_ns, p.T_world_cam) for i, p in poses.items()}
    missing = [i for i in range(n_frames) if i not in source]
    if missing:
        raise ServiceError(f"{len(missing)} of {n_frames} frames have no pose (first: {missing[:10]}); "
                           "was the replay faster than the service (queue drops on …/status) or "
                           "did the recorder start late? Raise --timeout or lower --rate")
    t_ns = np.array([source[i][0] for i in range(n_frames)], dtype=np.int64)
    T = np.array([source[i][1] for i in range(n_frames)], dtype=np.float64).reshape(n_frames, 4, 4)
    return t_ns, T


def write_poses(path: str | Path, fmt: str, poses: dict[int, PoseMessage],
                trajectory: TrajectoryMessage | None, n_frames: int) -> int:
    """Write frames ``0..n_frames-1`` to ``path`` as ``kitti`` or ``tum``; returns the count."""
    t_ns, T = poses_in_order(poses, trajectory, n_frames)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    if fmt == "kitti":
        write_kitti_poses(path, T)
    elif fmt == "tum":
        write_tum(path, t_ns, T)
    else:
        raise ServiceError(f"unknown pose format {fmt!r}; use kitti or tum")
    return n_frames
