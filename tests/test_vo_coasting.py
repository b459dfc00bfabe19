"""``MotionMemory`` (metricslam.slam.vo.coasting): where a camera that lost tracking went meanwhile."""

from __future__ import annotations

import numpy as np
from metricslam.geometry import se3, so3
from metricslam.slam.vo.coasting import MotionMemory

DT_NS = 100_000_000
STEP = se3.from_rt(so3.exp(np.array([0.0, 0.02, 0.0])), np.array([0.0, 0.0, 1.5]))  # per frame


def _tracked(memory: MotionMemory, n: int) -> np.ndarray:
    T = np.eye(4)
    for k in range(n):
        memory.tracked(STEP, k * DT_NS)
        T = T @ STEP
    return T


def test_a_lost_camera_keeps_its_motion_for_the_time_since_and_no_longer():
    memory = MotionMemory(max_s=2.0)
    T_last = _tracked(memory, 8)  # last tracked at frame 7
    memory.lost(STEP)
    assert np.isclose(memory.step_at_loss, 1.5)
    expected = T_last @ STEP @ STEP @ STEP  # three frame times later
    np.testing.assert_allclose(memory.pose_at(T_last, 10 * DT_NS), expected, atol=1e-9)
    np.testing.assert_allclose(memory.pose_at(T_last, 7 * DT_NS + 3 * 10**9), T_last)  # > 2 s: stays
    np.testing.assert_allclose(memory.pose_at(T_last, 6 * DT_NS), T_last)  # earlier: stays


def test_a_warp_rescales_what_is_kept_and_nothing_is_kept_before_a_loss():
    memory = MotionMemory(max_s=2.0)
    T_last = _tracked(memory, 6)
    np.testing.assert_allclose(memory.pose_at(T_last, 9 * DT_NS), T_last)  # never lost: no coasting
    memory.lost(STEP)
    memory.warp(2.0)  # the global graph made the units twice as fine
    T_last2 = T_last.copy()
    T_last2[:3, 3] *= 2.0
    moved = se3.inverse(T_last2) @ memory.pose_at(T_last2, 6 * DT_NS)  # one frame after frame 5
    assert np.isclose(np.linalg.norm(moved[:3, 3]), 3.0) and np.isclose(memory.step_at_loss, 3.0)
    still = MotionMemory(max_s=0.0)
    _tracked(still, 6)
    still.lost(STEP)
    np.testing.assert_allclose(still.pose_at(T_last, 6 * DT_NS), T_last)  # coast_max_s 0: where it was lost
