"""Turn recorded messages into files: a trajectory (KITTI or TUM), one line per frame, and an
MCAP recording for Foxglove (:func:`write_mcap`, docs/recordings.md)."""

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


def write_mcap(path: str | Path, camera_id: str, recorder, trajectory: TrajectoryMessage | None = None) -> dict:
    """Write what a :class:`~metricslam_slam.tools.client.PoseRecorder` (made with ``map_topics=True``)
    received as an MCAP file, the layout ``metricslam run --mcap`` writes: every pose, keyframe
    images (when the service attaches them: ``--keyframe-images``), keyframe depth maps,
    landmarks, every ``…/path`` update and, when given, ``trajectory`` as the final path.
    Messages are stamped (``log_time``) with their frame's ``t_ns``. Returns topic -> count."""
    from metricslam.ros2.mcap_log import McapLog

    with McapLog(path, camera_id=camera_id) as log:
        for i in sorted(recorder.poses):
            log.pose(recorder.poses[i].t_ns, recorder.poses[i].T_world_cam)
        for kf in recorder.keyframes:
            if kf.image is not None:
                log.keyframe_image(kf.t_ns, kf.image, None)
        for depth in recorder.depths:
            log.keyframe_depth(depth.t_ns, depth.inv_depth_per_m)
        for lm in recorder.landmarks:
            log.landmarks(lm.t_ns, lm.points_world)
        paths = list(recorder.paths) + ([trajectory] if trajectory is not None else [])
        for p in paths:
            if len(p.t_ns):
                log.path(int(p.t_ns.max()), p.t_ns, p.T_world_cam)
        return dict(log.counts)
