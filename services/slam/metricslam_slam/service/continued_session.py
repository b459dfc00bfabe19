"""A camera's new SLAM session that continues its earlier trajectory as a new linked segment.

Used when a camera's session is replaced while the camera goes on: the service restarted (poses
from the state directory), the camera came back after an idle close, or the session reached
``max_session_keyframes`` (:mod:`metricslam_slam.service.cameras`). The earlier poses (``prior``)
are kept as they are; the new session starts at its own origin, and its poses are mapped into the
earlier world frame by the last earlier pose, moved on by the camera's last velocity over the gap,
so its first pose is where the camera should be now (not the origin):

    T_world_cam = T_world_origin · T_origin_cam
    T_world_origin = last prior pose, its position + v · (t_first_new − t_last_prior)

``v`` (world units per second) is the mean velocity over the last :data:`VELOCITY_WINDOW_S` of
earlier poses; over a gap longer than :data:`MAX_EXTRAPOLATION_S` (or without two earlier poses
to measure ``v``) the camera is taken to have stayed where it was last seen. A moving camera
restarted after ~2–3 s (``kill -9`` and a restart by ``metricslam up``) otherwise lands tens of
metres behind itself (a car at 10 m/s). The orientation is the last one (turn rates are not
extrapolated). Its segment ids follow the earlier ones (a new segment: consumers can tell the
seam); the new segment has the monocular VO's arbitrary scale until learned scale factors
establish it again, like any new session.

A camera is continued only when its frames go on: :func:`why_new_session` names the reason
when a frame's index or timestamp goes backwards from the last earlier pose (a second replay of
a sequence, another sequence, a restarted camera); the service then starts a fresh session
(``session_restarted`` with a detail that starts "new session") instead of placing the new
frames after the old trajectory (``camera_worker.CameraWorker``).

The earlier poses are final, and a camera keeps them for as long as it runs (each roll-over
continues them all; ``…/trajectory`` answers them), so they are held as columns
(:class:`PoseTable`, ~170 bytes a pose instead of ~490 for a :class:`PoseEstimate` object and
its own array), and ``…/path`` takes their arrays as they are instead of rebuilding them from
every earlier pose at every keyframe (:meth:`ContinuedSession.path_columns`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from metricslam.datasets.base import Frame
from metricslam.errors import ServiceError
from metricslam.slam.types import PoseEstimate, ScaleState, SlamSession
from metricslam.wire.codec import STATE_CODES, TrajectoryMessage

_SCALE_STATES: tuple[ScaleState, ...] = tuple(ScaleState)
#: longest gap (s) between the last earlier pose and the first new frame that is bridged at the
#: camera's last velocity (a supervised restart takes ~2-3 s; an idle close is 120 s)
MAX_EXTRAPOLATION_S = 5.0
#: the camera's last velocity is its mean over this much of its last earlier poses (s)
VELOCITY_WINDOW_S = 1.0


def why_new_session(last_frame_index: int, last_t_ns: int, frame_index: int, t_ns: int) -> str | None:
    """Why a frame cannot continue a camera's trajectory whose last frame was
    ``(last_frame_index, last_t_ns)``, or None when it can (both go on; equal timestamps are
    allowed, a repeated frame index is not).

    >>> why_new_session(50, 5_000_000_000, 0, 0)
    'frame index went back from 50 to 0 (a new replay or sequence?)'
    >>> why_new_session(50, 5_000_000_000, 51, 5_100_000_000) is None
    True
    """
    if frame_index <= last_frame_index:
        return (f"frame index went back from {last_frame_index} to {frame_index} (a new replay or sequence?)"
                if frame_index < last_frame_index else f"frame index {frame_index} was sent again")
    if t_ns < last_t_ns:
        return (f"timestamp went back from {last_t_ns / 1e9:.3f} s to {t_ns / 1e9:.3f} s "
                "(a restarted camera or another sequence?)")
    return None


def anchor_pose(prior: list[PoseEstimate]) -> PoseEstimate:
    """The pose a continuation starts from: the last earlier pose that is a real one."""
    return next((p for p in reversed(prior) if p.pose_valid), prior[-1])


def last_velocity(prior: list[PoseEstimate], window_s: float = VELOCITY_WINDOW_S) -> np.ndarray | None:
    """Mean velocity (3,) world units/s of the camera over the last ``window_s`` of its real
    (``pose_valid``) poses, or None without two of them at least 50 ms apart in that window."""
    valid = [p for p in prior if p.pose_valid]
    if len(valid) < 2:
        return None
    last = valid[-1]
    first = next((p for p in valid if last.t_ns - p.t_ns <= window_s * 1e9), last)
    dt_s = (last.t_ns - first.t_ns) / 1e9
    if dt_s < 0.05:
        return None
    v = (np.asarray(last.T_world_cam, float)[:3, 3] - np.asarray(first.T_world_cam, float)[:3, 3]) / dt_s
    return v if np.isfinite(v).all() else None


class PoseTable:
    """Final poses, read-only, as columns: row ``k`` is ``poses[k]`` (:meth:`poses` gives them
    back as equal :class:`PoseEstimate` objects).

    Memory: ~170 bytes a pose (the (4, 4) float64 ``T_world_cam`` is 128 of them), against ~490
    for a :class:`PoseEstimate` with its own array; still one row per pose.

    Attributes:
        frame_index, t_ns, segment_id, scale_factors: (N,) int64.
        T_world_cam: (N, 4, 4) float64.
        state_code: (N,) uint8 index into :data:`metricslam.wire.codec.STATE_CODES`.
        scale_state_code: (N,) uint8 index into :class:`ScaleState`'s members.
        is_keyframe, scale_established, interpolated, pose_valid: (N,) bool.
    """

    def __init__(self, poses: list[PoseEstimate]) -> None:
        n = len(poses)

        def column(field: str, dtype) -> np.ndarray:
            return np.fromiter((getattr(p, field) for p in poses), dtype=dtype, count=n)

        self.frame_index = column("frame_index", np.int64)
        self.t_ns = column("t_ns", np.int64)
        self.T_world_cam = np.array([np.asarray(p.T_world_cam, dtype=np.float64) for p in poses],
                                    dtype=np.float64).reshape(n, 4, 4)
        self.state_code = TrajectoryMessage.state_codes([p.state for p in poses])
        self.is_keyframe = column("is_keyframe", bool)
        self.segment_id = column("segment_id", np.int64)
        self.scale_established = column("scale_established", bool)
        self.interpolated = column("interpolated", bool)
        self.pose_valid = column("pose_valid", bool)
        self.scale_state_code = np.fromiter((_SCALE_STATES.index(ScaleState(p.scale_state)) for p in poses),
                                            dtype=np.uint8, count=n)
        self.scale_factors = column("scale_factors", np.int64)

    def __len__(self) -> int:
        return len(self.frame_index)

    @property
    def nbytes(self) -> int:
        """Bytes of array data held."""
        return sum(a.nbytes for a in vars(self).values() if isinstance(a, np.ndarray))

    def poses(self) -> list[PoseEstimate]:
        """Every row as a :class:`PoseEstimate` (each with its own ``T_world_cam`` array)."""
        rows = zip(self.frame_index.tolist(), self.t_ns.tolist(), self.T_world_cam, self.state_code.tolist(),
                   self.is_keyframe.tolist(), self.segment_id.tolist(), self.scale_established.tolist(),
                   self.interpolated.tolist(), self.pose_valid.tolist(), self.scale_state_code.tolist(),
                   self.scale_factors.tolist())
        return [PoseEstimate(f, t, T.copy(), STATE_CODES[s], is_keyframe=kf, segment_id=seg, scale_established=est,
                             interpolated=interp, pose_valid=valid, scale_state=_SCALE_STATES[ss], scale_factors=nf)
                for f, t, T, s, kf, seg, est, interp, valid, ss, nf in rows]


class ContinuedSession:
    """A :class:`~metricslam.slam.types.SlamSession` continuing ``prior`` (module docstring).

    Args:
        inner: the new session (its own origin and segment ids).
        prior: the camera's earlier poses, in order (not empty).

    Attributes:
        prior: the earlier poses (:class:`PoseTable`).
        T_world_origin: (4, 4) maps the inner session's world frame into the earlier one.
        first_segment_id: the inner session's segment 0 is published as this segment id.
    """

    def __init__(self, inner: SlamSession, prior: list[PoseEstimate]) -> None:
        if not prior:
            raise ServiceError("a continued session needs earlier poses")
        self.inner = inner
        self.prior = PoseTable(prior)
        self.anchor = anchor_pose(prior)
        self.T_world_origin = np.asarray(self.anchor.T_world_cam, dtype=np.float64).copy()
        self.first_segment_id = int(self.prior.segment_id.max()) + 1
        self._velocity = last_velocity(prior)
        self.extrapolated_m = 0.0  # how far the origin was moved on over the gap (world units)
        self._linked = False

    def _mapped(self, est: PoseEstimate) -> PoseEstimate:
        return dataclasses.replace(est, T_world_cam=self.T_world_origin @ np.asarray(est.T_world_cam),
                                   segment_id=est.segment_id + self.first_segment_id)

    def process(self, frame: Frame) -> PoseEstimate:
        if not self._linked:
            self._link(frame.t_ns)
        return self._mapped(self.inner.process(frame))

    def _link(self, t_first_ns: int) -> None:
        """Move the origin on by the camera's last velocity over the gap to the first new frame."""
        self._linked = True
        gap_s = (int(t_first_ns) - self.anchor.t_ns) / 1e9
        if self._velocity is None or not 0.0 < gap_s <= MAX_EXTRAPOLATION_S:
            return
        step = self._velocity * gap_s
        self.T_world_origin[:3, 3] += step
        self.extrapolated_m = float(np.linalg.norm(step))

    def trajectory(self) -> list[PoseEstimate]:
        """The earlier poses, then the new session's current best poses (mapped)."""
        return self.prior.poses() + self.current_trajectory()

    def current_trajectory(self) -> list[PoseEstimate]:
        """The new session's current best poses (mapped), without the earlier ones."""
        return [self._mapped(e) for e in self.inner.trajectory()]

    def path_columns(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
        """``(frame_index, t_ns, T_world_cam, state_code, scale_established)`` of the
        :meth:`trajectory` poses with ``pose_valid`` (the ``…/path`` message's arrays; the
        flag: that of the last of them), from the earlier poses' stored columns."""
        p, valid = self.prior, self.prior.pose_valid
        f0, t0, T0, s0 = p.frame_index[valid], p.t_ns[valid], p.T_world_cam[valid], p.state_code[valid]
        kept = [e for e in self.current_trajectory() if e.pose_valid]
        if not kept:
            return f0, t0, T0, s0, bool(p.scale_established[valid][-1:].any())
        n = len(kept)
        return (np.concatenate([f0, np.array([e.frame_index for e in kept], dtype=np.int64)]),
                np.concatenate([t0, np.array([e.t_ns for e in kept], dtype=np.int64)]),
                np.concatenate([T0, np.array([e.T_world_cam for e in kept], dtype=np.float64).reshape(n, 4, 4)]),
                np.concatenate([s0, TrajectoryMessage.state_codes([e.state for e in kept])]),
                bool(kept[-1].scale_established))

    def stats(self) -> dict:
        stats = dict(self.inner.stats())
        stats["continued"] = {"prior_poses": len(self.prior), "first_segment_id": self.first_segment_id,
                              "anchor_frame_index": self.anchor.frame_index,
                              "extrapolated_m": self.extrapolated_m}
        return stats

    def close(self) -> None:
        self.inner.close()

    def __getattr__(self, name: str):
        # the back end, VO, ... of the inner session (map topics, viewer); only reached for
        # names this class does not define
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)
