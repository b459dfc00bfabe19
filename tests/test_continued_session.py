"""A camera's earlier poses across session roll-overs (``ContinuedSession``): what each new
session keeps of them, and that its trajectory and ``…/path`` arrays are the same as built pose
by pose. Each roll-over continues *all* earlier poses, for as long as the camera runs."""

from __future__ import annotations

import dataclasses
import gc
import tracemalloc

import numpy as np
import pytest

from metricslam.slam.types import PoseEstimate, ScaleState, TrackingState
from metricslam.wire.codec import TrajectoryMessage
from metricslam_slam.service.continued_session import ContinuedSession

FRAMES_PER_SESSION = 3000


def _pose(i: int, rng: np.random.Generator) -> PoseEstimate:
    T = np.eye(4)
    T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    T[:3, 3] = rng.normal(size=3)
    return PoseEstimate(i, i * 100_000_000 + 7, T, list(TrackingState)[i % 4], is_keyframe=i % 3 == 0,
                        segment_id=i // 700, scale_established=i % 5 == 0, interpolated=i % 7 == 0,
                        pose_valid=i % 11 != 0, scale_state=list(ScaleState)[i % 3], scale_factors=i % 13)


class _Session:
    """A session's own poses (its ``trajectory``), in its own world frame."""

    def __init__(self, first: int, n: int, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self.poses = [_pose(first + i, rng) for i in range(n)]

    def trajectory(self) -> list[PoseEstimate]:
        return list(self.poses)

    def close(self) -> None:
        pass


def test_earlier_poses_are_held_in_at_most_200_bytes_each_across_roll_overs() -> None:
    """Four roll-overs as ``CameraWorker._roll_over`` does them (close, continue the whole
    trajectory, drop the old session): the session holds each earlier pose in at most 200
    bytes (as ``PoseEstimate`` objects with their own arrays: ~490)."""
    gc.collect()
    tracemalloc.start()
    try:
        session = ContinuedSession(_Session(FRAMES_PER_SESSION, FRAMES_PER_SESSION, 1),
                                   _Session(0, FRAMES_PER_SESSION, 0).trajectory())
        for k in range(2, 5):
            session.close()
            prior = session.trajectory()
            session = ContinuedSession(_Session(k * FRAMES_PER_SESSION, FRAMES_PER_SESSION, k), prior)
            del prior
        session.inner.poses = []  # count only the earlier poses
        gc.collect()
        held = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    earlier = 4 * FRAMES_PER_SESSION
    assert len(session.prior) == earlier
    assert held <= 200 * earlier, f"{held / earlier:.0f} bytes per earlier pose"


def test_trajectory_and_path_are_the_poses_built_one_by_one() -> None:
    prior = _Session(0, 1000, 0).trajectory()
    inner = _Session(1000, 100, 1)
    session = ContinuedSession(inner, prior)
    mapped = [dataclasses.replace(e, T_world_cam=session.T_world_origin @ e.T_world_cam,
                                  segment_id=e.segment_id + session.first_segment_id) for e in inner.poses]
    expected = prior + mapped
    got = session.trajectory()
    assert len(got) == len(expected) == 1100 and session.first_segment_id == 2
    for a, b in zip(expected, got):
        for field in dataclasses.fields(PoseEstimate):
            va, vb = getattr(a, field.name), getattr(b, field.name)
            if field.name == "T_world_cam":
                assert vb.dtype == np.float64 and np.array_equal(va, vb)
            else:
                assert va == vb and type(va) is type(vb), field.name
    kept = [e for e in expected if e.pose_valid]
    frame_index, t_ns, T_world_cam, state_code, scale_established = session.path_columns()
    assert np.array_equal(frame_index, [e.frame_index for e in kept]) and frame_index.dtype == np.int64
    assert np.array_equal(t_ns, [e.t_ns for e in kept]) and t_ns.dtype == np.int64
    assert np.array_equal(T_world_cam, np.array([e.T_world_cam for e in kept]))
    assert np.array_equal(state_code, TrajectoryMessage.state_codes([e.state for e in kept]))
    assert scale_established is kept[-1].scale_established
    inner.poses = [dataclasses.replace(inner.poses[0], pose_valid=False)]  # no valid pose of its own yet
    assert session.path_columns()[4] is [e for e in prior if e.pose_valid][-1].scale_established
    assert len(session.path_columns()[0]) == len([e for e in prior if e.pose_valid])


def test_map_publisher_path_of_a_continued_session() -> None:
    from metricslam_slam.service.map_publisher import MapPublisher

    prior = _Session(0, 500, 0).trajectory()
    session = ContinuedSession(_Session(500, 50, 1), prior)
    sent = []
    MapPublisher("cam0", session, lambda topic, msg: sent.append((topic, msg)))._publish_path()
    kept = [e for e in session.trajectory() if e.pose_valid]
    (topic, msg), = sent
    assert topic == "path" and msg.camera_id == "cam0" and msg.scale_established is kept[-1].scale_established
    assert np.array_equal(msg.frame_index, [e.frame_index for e in kept])
    assert np.array_equal(msg.t_ns, [e.t_ns for e in kept])
    assert np.array_equal(msg.T_world_cam, np.array([e.T_world_cam for e in kept]))
    assert msg.states == [e.state for e in kept]


def _moving(first: int, n: int, v_m_per_frame: float, dt_s: float = 0.1) -> list[PoseEstimate]:
    out = []
    for i in range(first, first + n):
        T = np.eye(4)
        T[0, 3] = v_m_per_frame * i
        out.append(PoseEstimate(i, round(i * dt_s * 1e9), T, TrackingState.TRACKING))
    return out


def _first_new_x(prior: list[PoseEstimate], t_first_ns: int) -> float:
    from metricslam.datasets.base import Frame

    class _AtOrigin(_Session):
        def process(self, frame):
            return PoseEstimate(frame.index, frame.t_ns, np.eye(4), TrackingState.TRACKING)

    session = ContinuedSession(_AtOrigin(0, 0, 0), prior)
    est = session.process(Frame(index=prior[-1].frame_index + 1, t_ns=t_first_ns, image=np.zeros((4, 4), np.uint8),
                                camera=None))
    return float(est.T_world_cam[0, 3])


def test_the_seam_is_bridged_at_the_last_velocity_over_a_short_gap_only() -> None:
    """A camera moving 1 m a frame (10 m/s) whose session is replaced: after a 2 s gap (a
    supervised restart) the new segment starts 20 m on; after a gap longer than
    MAX_EXTRAPOLATION_S, or for a camera that stood still, where it was last seen."""
    from metricslam_slam.service.continued_session import MAX_EXTRAPOLATION_S

    prior = _moving(0, 50, 1.0)  # last pose x = 49 m at t = 4.9 s
    assert _first_new_x(prior, prior[-1].t_ns + 100_000_000) == pytest.approx(50.0)  # roll-over: next frame
    assert _first_new_x(prior, prior[-1].t_ns + 2_000_000_000) == pytest.approx(69.0)
    assert _first_new_x(prior, prior[-1].t_ns + int((MAX_EXTRAPOLATION_S + 1) * 1e9)) == pytest.approx(49.0)
    assert _first_new_x(_moving(0, 50, 0.0), prior[-1].t_ns + 2_000_000_000) == pytest.approx(0.0)
    assert _first_new_x(prior[:1], prior[0].t_ns + 2_000_000_000) == pytest.approx(0.0)  # no velocity known
