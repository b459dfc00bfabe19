"""The global graph's warp (``LocalVO.apply_similarity``) against keyframes that the BA worker
marginalized but the VO has not delivered yet: they must reach the consumer in the *new* VO
frame, consistent with the keyframes delivered before the warp (issue 6 follow-up)."""

from __future__ import annotations

import numpy as np
import pytest

from metricslam.geometry import se3, sim3
from metricslam.slam.types import MarginalizedKeyframe, TrackingState
from metricslam.slam.vo.config import VOConfig
from metricslam.slam.vo.local_vo import LocalVO


class _Sink:
    def __init__(self) -> None:
        self.kfs: list[MarginalizedKeyframe] = []

    def on_keyframe_marginalized(self, kf: MarginalizedKeyframe) -> None:
        self.kfs.append(kf)


@pytest.fixture(scope="module")
def kitti06(shared_data):
    from metricslam.datasets import open_sequence
    return open_sequence(shared_data / "kitti_odometry" / "sequences" / "06")


def _warp_rigid(S: np.ndarray, T: np.ndarray) -> np.ndarray:
    """conventions.md: rotation ``R_S·R``, position ``S·t`` (a rigid pose in the new frame)."""
    s = sim3.scale(S)
    out = np.eye(4)
    out[:3, :3] = S[:3, :3] / s @ T[:3, :3]
    out[:3, 3] = sim3.transform_points(S, T[:3, 3])
    return out


def test_keyframes_queued_by_the_worker_are_warped_before_delivery(kitti06) -> None:
    """Race made deterministic: the worker marginalizes into the outbox after ``process`` has
    delivered, the pipeline warps, the next ``process`` delivers."""
    sink = _Sink()
    vo = LocalVO(VOConfig.preset("kitti", window_size=3, ba_in_background=True), kitti06.camera,
                 consumer=sink)
    S = sim3.from_rts(se3.exp(np.r_[0.05, -0.1, 0.2, 0, 0, 0])[:3, :3], np.r_[3.0, -1.0, 2.0], 2.5)
    queued: list[MarginalizedKeyframe] = []
    i = 0
    # wait for a queued keyframe that has a delivered predecessor (T_prevkf_kf set)
    while not any(k.T_prevkf_kf is not None for k in queued) and i < 40:
        assert vo.process(kitti06[i]).state is not TrackingState.LOST
        vo._worker.wait_idle()  # the solve and its marginalization finish after the delivery
        with vo.window.lock:
            queued = list(vo.window.outbox)
        i += 1
    assert any(k.T_prevkf_kf is not None for k in queued), "no keyframe queued within 40 frames"
    delivered_before = list(sink.kfs)
    frozen_before = vo.keyframe_poses()
    vo.apply_similarity(S)
    vo.process(kitti06[i])  # delivers the queued keyframes (and maybe more)
    vo.close()
    s = sim3.scale(S)
    got = {k.kf_id: k for k in sink.kfs}
    for old in queued:
        new = got[old.kf_id]
        np.testing.assert_allclose(new.T_vo_kf, _warp_rigid(S, old.T_vo_kf), atol=1e-9)
        np.testing.assert_allclose(new.landmarks_inv_depth, old.landmarks_inv_depth / s, rtol=1e-12)
        np.testing.assert_array_equal(new.landmarks_uv_px, old.landmarks_uv_px)
        # keyframe_poses() of an undelivered keyframe follows the warp as well
        np.testing.assert_allclose(vo.keyframe_poses()[old.frame_index],
                                   _warp_rigid(S, frozen_before[old.frame_index]), atol=1e-9)
    # the relative poses chain in the new frame, across the warp: a keyframe delivered before
    # the warp, seen in the new frame, composed with the next one's T_prevkf_kf
    seq = sorted(sink.kfs, key=lambda k: k.kf_id)
    first_queued = min(k.kf_id for k in queued)
    checked = 0
    for prev, kf in zip(seq, seq[1:]):
        if kf.kf_id < first_queued or kf.T_prevkf_kf is None:
            continue
        checked += 1
        T_prev = prev.T_vo_kf
        if prev.kf_id in {k.kf_id for k in delivered_before}:
            T_prev = _warp_rigid(S, T_prev)
        np.testing.assert_allclose(T_prev @ kf.T_prevkf_kf, kf.T_vo_kf, atol=1e-8)
    assert checked >= 1
