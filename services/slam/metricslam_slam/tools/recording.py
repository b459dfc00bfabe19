"""Turn recorded messages into files: a trajectory (KITTI or TUM), one line per frame, and an
MCAP recording for Foxglove (:func:`write_mcap`, docs/recordings.md).

What gets recorded: :func:`unscaled_frames` names the frames whose pose has no metric scale
(``PoseMessage.scale_state`` ``unscaled``: the VO's arbitrary units, no depth source, or the VO
had no map yet); ``metricslam poses`` leaves them out unless ``--all`` (:func:`write_poses`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from metricslam.errors import ServiceError
from metricslam.slam.types import ScaleState
from metricslam.trajectory.io import write_kitti_poses, write_tum
from metricslam.wire.codec import PoseMessage, TrajectoryMessage


def unscaled_frames(poses: dict[int, PoseMessage], trajectory: TrajectoryMessage | None,
                    n_frames: int) -> list[int]:
    """Frames ``0..n_frames-1`` whose pose is ``unscaled``: by each live pose's scale state
    (:meth:`PoseMessage.effective_scale_state`), or, for an optimized ``trajectory``, every frame
    when its scale is not established (it carries one flag for the whole trajectory)."""
    if trajectory is not None:
        return [] if trajectory.scale_established else list(range(n_frames))
    return [i for i in range(n_frames)
            if i in poses and poses[i].effective_scale_state() is ScaleState.UNSCALED]


def _source(poses: dict[int, PoseMessage], trajectory: TrajectoryMessage | None) -> dict[int, tuple]:
    if trajectory is not None:
        return {int(i): (int(t), T) for i, t, T in
                zip(trajectory.frame_index, trajectory.t_ns, trajectory.T_world_cam)}
    return {i: (p.t_ns, p.T_world_cam) for i, p in poses.items()}


def missing_frames(poses: dict[int, PoseMessage], trajectory: TrajectoryMessage | None,
                   n_frames: int) -> list[int]:
    """Frames ``0..n_frames-1`` with no pose in ``trajectory`` (if given) or the live ``poses``."""
    source = _source(poses, trajectory)
    return [i for i in range(n_frames) if i not in source]


def missing_error(missing: list[int], n_frames: int, restart: str | None = None) -> ServiceError:
    """The error naming frames without a pose; ``restart``: why the SLAM service looks restarted
    meanwhile (:func:`~metricslam_slam.tools.client.service_restart`), named as the cause."""
    head = f"{len(missing)} of {n_frames} frames have no pose (first: {missing[:10]})"
    if restart is not None:
        return ServiceError(f"{head}: the SLAM service restarted during the recording ({restart}); frames sent "
                            "while it was down or queued in it are lost: record and replay again")
    return ServiceError(f"{head}; was the replay faster than the service (queue drops on …/status) or "
                        "did the recorder start late? Raise --timeout or lower --rate")


def poses_in_order(poses: dict[int, PoseMessage], trajectory: TrajectoryMessage | None,
                   n_frames: int, fill_missing: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(t_ns (N,), T_world_cam (N, 4, 4))`` of frames ``0..n_frames-1`` in frame order, from
    ``trajectory`` if given else from the live ``poses``. ``fill_missing``: a frame without a pose
    gets ``t_ns`` 0 and the identity (the caller marks it, :func:`missing_frames`).

    Raises:
        ServiceError: a frame has no pose and ``fill_missing`` is False (names the first ones).
    """
    source = _source(poses, trajectory)
    missing = [i for i in range(n_frames) if i not in source]
    if missing and not fill_missing:
        raise missing_error(missing, n_frames)
    blank = (0, np.eye(4))
    t_ns = np.array([source.get(i, blank)[0] for i in range(n_frames)], dtype=np.int64)
    T = np.array([source.get(i, blank)[1] for i in range(n_frames)], dtype=np.float64).reshape(n_frames, 4, 4)
    return t_ns, T


def write_poses(path: str | Path, fmt: str, poses: dict[int, PoseMessage],
                trajectory: TrajectoryMessage | None, n_frames: int, skip: list[int] = (),
                missing_ok: bool = False) -> int:
    """Write frames ``0..n_frames-1`` except ``skip`` to ``path`` as ``kitti`` or ``tum``;
    returns the number of poses written. ``missing_ok``: frames without any pose are treated
    like ``skip`` (written what arrived; the caller still reports them, :func:`missing_frames`)
    instead of refusing to write anything.

    TUM lines carry their timestamp, so a skipped frame is simply left out. A KITTI file has one
    line per frame and no frame numbers (evaluation pairs it with the ground truth line by line),
    so a skipped frame keeps its line with a placeholder, as ``metricslam run`` does for frames
    without a pose: the previous written pose, or the world origin (identity: where the VO's
    first keyframe sits) before the first one.

    Raises:
        ServiceError: a frame has no pose at all, every frame is skipped, or ``fmt`` is unknown.
    """
    if fmt not in ("kitti", "tum"):
        raise ServiceError(f"unknown pose format {fmt!r}; use kitti or tum")
    missing = missing_frames(poses, trajectory, n_frames)
    if missing and (not missing_ok or len(missing) == n_frames):
        raise missing_error(missing, n_frames)
    t_ns, T = poses_in_order(poses, trajectory, n_frames, fill_missing=True)
    keep = np.ones(n_frames, dtype=bool)
    keep[[i for i in list(skip) + missing if 0 <= i < n_frames]] = False
    if not keep.any():
        raise ServiceError(f"all {n_frames} poses are unscaled (no metric scale: is the depth "
                           "service reachable? see …/status depth_reachable); --all records them")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    if fmt == "tum":
        write_tum(path, t_ns[keep], T[keep])
    else:
        write_kitti_poses(path, _with_placeholders(T, keep))
    return int(keep.sum())


def _with_placeholders(T: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(N, 4, 4) ``T`` with every frame not kept replaced by the previous kept pose (identity
    before the first)."""
    out = np.array(T, copy=True)
    last = np.eye(4)
    for i in range(len(out)):
        if keep[i]:
            last = out[i]
        else:
            out[i] = last
    return out


def write_mcap(path: str | Path, camera_id: str, recorder, trajectory: TrajectoryMessage | None = None) -> dict:
    """Write what a :class:`~metricslam_slam.tools.client.PoseRecorder` (made with ``map_topics=True``)
    received as an MCAP file, the layout ``metricslam run --mcap`` writes: every pose, keyframe
    images (when the service attaches them: ``--keyframe-images``), keyframe depth maps,
    landmarks, every ``…/path`` update and, when given, ``trajectory`` as the final path.
    Messages are stamped (``log_time``) with their frame's ``t_ns``; each keeps its message's
    ``frame_id`` (parent frame ``map`` once the camera relocalized into the service's map, else
    ``<cam>/world``, as the live ROS 2 bridge names it). Returns topic -> count."""
    from metricslam.ros2.mcap_log import McapLog

    with McapLog(path, camera_id=camera_id) as log:
        for i in sorted(recorder.poses):
            pose = recorder.poses[i]
            log.pose(pose.t_ns, pose.T_world_cam, pose.frame_id)
        for kf in recorder.keyframes:
            if kf.image is not None:
                log.keyframe_image(kf.t_ns, kf.image, None)
        for depth in recorder.depths:
            log.keyframe_depth(depth.t_ns, depth.inv_depth_per_m)
        for lm in recorder.landmarks:
            log.landmarks(lm.t_ns, lm.points_world, lm.frame_id)
        paths = list(recorder.paths) + ([trajectory] if trajectory is not None else [])
        for p in paths:
            if len(p.t_ns):
                log.path(int(p.t_ns.max()), p.t_ns, p.T_world_cam, p.frame_id)
        return dict(log.counts)
