"""Properties of the continuous odometry stream (metricslam.trajectory.continuous)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from metricslam.geometry import se3, sim3, so3
from metricslam.slam.events import EventBus, InitialScaleApplied, WarpApplied
from metricslam.slam.types import PoseEstimate, ScaleState, TrackingState
from metricslam.trajectory.continuous import (
    ContinuousOdometry,
    ContinuousOdometryConfig,
    apply_sim3_rigid,
)

DT_NS = 100_000_000  # 10 Hz


def drive(n: int, seed: int = 0, speed_mps: float = 10.0) -> np.ndarray:
    """(n, 4, 4) ``T_world_cam`` of a camera driving forward (z) with a wobbling yaw rate,
    starting 30 m from the world origin (so a scale change moves it by metres)."""
    rng = np.random.default_rng(seed)
    T = se3.from_rt(so3.exp([0.0, 0.3, 0.0]), [30.0, 0.0, 5.0])
    out = []
    for _ in range(n):
        out.append(T.copy())
        yaw_rate = 0.2 * np.sin(len(out) / 15.0) + 0.02 * rng.standard_normal()
        step = se3.exp([0.0, yaw_rate * 0.1, 0.0, 0.0, 0.0, speed_mps * 0.1])
        T = T @ step
    return np.array(out)


def est(k: int, T: np.ndarray, state: TrackingState = TrackingState.TRACKING, segment: int = 0) -> PoseEstimate:
    return PoseEstimate(frame_index=k, t_ns=k * DT_NS, T_world_cam=T, state=state, segment_id=segment,
                        scale_state=ScaleState.METRIC)


def random_warp(rng: np.random.Generator, s: float) -> np.ndarray:
    return sim3.from_rts(so3.exp(0.03 * rng.standard_normal(3)), 2.0 * rng.standard_normal(3), s)


def steps_m(T: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)


def run(live: list[PoseEstimate], warps: dict[int, np.ndarray], config=None):
    odom = ContinuousOdometry(config)
    out = []
    for e in live:
        if e.frame_index in warps:
            odom.on_correction(warps[e.frame_index])
        out.append(odom.update(e))
    return odom, out


def test_identity_without_corrections_bit_for_bit():
    truth = drive(200)
    _, out = run([est(k, T) for k, T in enumerate(truth)], {})
    for T, c in zip(truth, out):
        assert np.array_equal(c.T_world_cam, T)
        assert np.array_equal(c.T_world_odom, np.eye(4))
        assert c.correction_m == 0.0
    # twist: forward at 10 m/s in the camera frame
    assert out[50].twist_cam[5] == pytest.approx(10.0, rel=1e-6)
    assert np.abs(out[50].twist_cam[3:5]).max() < 1e-6


@pytest.mark.parametrize("s", [1.15, 0.8, 3.0])
def test_continuity_across_a_scale_jump(s):
    """Each step is at most the true step plus the jump's share of one frame (dt / horizon), and a
    jump too large for the horizon is blended no faster than half the camera's speed: within 2x
    the true per-frame motion whatever the jump (x3 moves the camera 60 m)."""
    rng = np.random.default_rng(1)
    truth = drive(120, seed=1)
    k_warp = 40
    S = random_warp(rng, s)
    live = [est(k, T if k < k_warp else apply_sim3_rigid(S, T)) for k, T in enumerate(truth)]
    raw = np.array([e.T_world_cam for e in live])
    assert steps_m(raw).max() > 4.0  # the live stream really jumps
    _, out = run(live, {k_warp: S})
    cont = np.array([c.T_world_cam for c in out])
    # after the warp the world unit is s times smaller: true motion there is s x 1 m per frame
    true_max = max(steps_m(truth).max(), s * steps_m(truth).max())
    jump = np.linalg.norm(raw[k_warp, :3, 3] - apply_sim3_rigid(S, truth[k_warp - 1])[:3, 3])
    bound = true_max + 1.05 * (np.linalg.norm(raw[k_warp, :3, 3] - raw[k_warp - 1, :3, 3]) + jump) * 0.1 / 2.0
    assert steps_m(cont).max() <= bound
    assert steps_m(cont).max() <= 2.0 * true_max
    # and it is fully blended in within max_horizon_s (10 s) of the warp
    assert out[k_warp].blend_until_t_ns <= live[k_warp - 1].t_ns + 10 * 10**9


def test_a_large_correction_takes_longer_than_the_horizon_a_small_one_does_not():
    rng = np.random.default_rng(4)
    truth = drive(200, seed=4)  # 1 m per frame at 10 Hz: 10 m/s
    for s, slower in ((1.05, False), (3.0, True)):
        S = random_warp(rng, s)
        live = [est(k, T if k < 60 else apply_sim3_rigid(S, T)) for k, T in enumerate(truth)]
        _, out = run(live, {60: S})
        blend_s = (out[60].blend_until_t_ns - live[59].t_ns) / 1e9
        assert (blend_s > 2.0 + 1e-9) is slower and blend_s <= 10.0 + 1e-9, (s, blend_s)


def test_converges_to_the_live_pose_within_the_horizon():
    rng = np.random.default_rng(2)
    truth = drive(150, seed=2)
    config = ContinuousOdometryConfig(horizon_s=1.5)
    warps = {30: random_warp(rng, 1.2), 37: random_warp(rng, 0.9)}
    S_total, live = np.eye(4), []
    for k, T in enumerate(truth):
        if k in warps:
            S_total = warps[k] @ S_total
        live.append(est(k, apply_sim3_rigid(S_total, T) if k >= 30 else T))
    _, out = run(live, warps, config)
    done_k = 37 - 1 + int(round(1.5 / 0.1))  # the last blend started at frame 36's time
    assert out[done_k - 2].correction_m > 1e-3  # still blending shortly before
    for e, c in zip(live[done_k:], out[done_k:]):
        np.testing.assert_allclose(c.T_world_cam, e.T_world_cam, atol=1e-9)
        assert c.correction_m < 1e-9
        assert c.blend_until_t_ns <= e.t_ns


def test_relative_motion_across_the_warp_is_the_pre_correction_pair_in_new_units():
    truth = drive(60)
    S = sim3.from_rts(np.eye(3), np.zeros(3), 2.0)
    live = [est(k, T if k < 20 else apply_sim3_rigid(S, T)) for k, T in enumerate(truth)]
    _, out = run(live, {20: S})
    T_rel = se3.inverse(out[19].T_odom_cam) @ out[20].T_odom_cam
    T_rel_true = se3.inverse(truth[19]) @ truth[20]
    np.testing.assert_allclose(T_rel[:3, :3], T_rel_true[:3, :3], atol=1e-9)
    np.testing.assert_allclose(T_rel[:3, 3], 2.0 * T_rel_true[:3, 3], atol=1e-9)
    assert out[20].twist_cam[5] == pytest.approx(20.0, rel=1e-3)


def test_new_segment_holds_then_blends_and_lost_frames_hold():
    truth = drive(100)
    live = [est(k, T, segment=0) for k, T in enumerate(truth[:30])]
    live += [est(k, truth[k], TrackingState.LOST, segment=0) for k in range(30, 33)]
    offset = se3.from_rt(so3.exp([0, 0.1, 0]), [5.0, 0, 0])  # the new segment's world is off
    live += [est(k, offset @ truth[k], segment=1) for k in range(33, 100)]
    _, out = run(live, {})
    cont = np.array([c.T_world_cam for c in out])
    for k in range(30, 34):  # lost frames and the seam frame: no odometry motion
        assert np.abs(out[k].twist_cam).max() < 1e-12
    assert steps_m(cont).max() <= 2.0 * steps_m(truth).max()
    np.testing.assert_allclose(cont[-1], live[-1].T_world_cam, atol=1e-9)


def test_before_tracking_the_live_pose_is_passed_through():
    truth = drive(10)
    live = [est(0, np.eye(4), TrackingState.INITIALIZING)] + [est(k, T) for k, T in enumerate(truth[1:], 1)]
    _, out = run(live, {})
    assert np.array_equal(out[0].T_world_cam, np.eye(4))
    assert np.array_equal(out[5].T_world_cam, truth[5])


def test_attach_takes_corrections_from_the_back_end_events():
    bus = EventBus()
    odom = ContinuousOdometry()
    assert odom.attach(SimpleNamespace(backend=SimpleNamespace(events=bus)))
    assert not ContinuousOdometry().attach(SimpleNamespace(backend=None))
    truth = drive(40)
    for k in range(20):
        odom.update(est(k, truth[k]))
    bus.emit(InitialScaleApplied(kf_frame_index=0, frame_index=20, scale=2.0, n_landmarks=10, wait_ms=1.0))
    S = np.diag([2.0, 2.0, 2.0, 1.0])
    c = odom.update(est(20, apply_sim3_rigid(S, truth[20])))
    assert odom.corrections == 1
    live_jump = np.linalg.norm(apply_sim3_rigid(S, truth[20])[:3, 3] - truth[19][:3, 3])
    step = np.linalg.norm(c.T_world_cam[:3, 3] - truth[19][:3, 3])
    # one frame in new units (2 m) plus a twentieth (dt / horizon) of the ~40 m jump
    assert live_jump > 40.0 and step <= 2.0 + live_jump / 20.0
    assert c.correction_m > 0.9 * (live_jump - 2.0) * 19 / 20
    S2 = sim3.from_rts(np.eye(3), [1.0, 0, 0], 1.0)
    bus.emit(WarpApplied(S2, 1.0, 1))
    assert odom.corrections == 2


def test_continued_session_warps_are_conjugated_into_the_outer_world():
    bus = EventBus()
    T_wo = se3.from_rt(so3.exp([0, 1.0, 0]), [100.0, 0, -20.0])
    session = SimpleNamespace(backend=SimpleNamespace(events=bus), T_world_origin=T_wo)
    odom = ContinuousOdometry()
    odom.attach(session)
    truth_inner = drive(40)
    for k in range(20):
        odom.update(est(k, T_wo @ truth_inner[k]))
    S = sim3.from_rts(np.eye(3), np.zeros(3), 1.5)  # the inner world scaled about ITS origin
    bus.emit(WarpApplied(S, 1.5, 1))
    c = odom.update(est(20, T_wo @ apply_sim3_rigid(S, truth_inner[20])))
    T_rel = se3.inverse(truth_inner[19]) @ truth_inner[20]
    assert np.linalg.norm(c.twist_cam[3:] * 0.1) == pytest.approx(1.5 * np.linalg.norm(T_rel[:3, 3]), rel=1e-3)
