"""Loop detection on real KITTI images: a revisit is found with the right Sim(3), a new place is not.

Landmarks are Shi-Tomasi corners with metric depth from stereo block matching (so the true
relative Sim(3) has scale 1 and the ground-truth poses check it).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from metricslam.geometry import se3, sim3
from metricslam.slam.graph.config import LoopConfig
from metricslam.slam.loop import LoopDetector

CONFIG = LoopConfig(skip_recent_keyframes=8, vocabulary_train_keyframes=6, vocabulary_words=200,
                    keyframe_stride=1)


def _landmarks(frame) -> tuple[np.ndarray, np.ndarray]:
    """Corners (M, 2) and their metric inverse depth (M,) from SGBM on the stereo pair."""
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=64, blockSize=7, P1=8 * 49,
                                 P2=32 * 49, uniquenessRatio=10, speckleWindowSize=50, speckleRange=2)
    disp = sgbm.compute(frame.image, frame.image_right).astype(np.float32) / 16.0
    corners = cv2.goodFeaturesToTrack(frame.image, 300, 0.01, 10).reshape(-1, 2)
    d = disp[corners[:, 1].round().astype(int), corners[:, 0].round().astype(int)]
    ok = d > 2.0
    inv_depth = d[ok] / (frame.camera.fx_px * frame.baseline_m)
    return corners[ok].astype(float), inv_depth


@pytest.fixture(scope="module")
def kitti06(shared_data):
    from metricslam.datasets.kitti import KittiOdometry

    seq_dir = shared_data / "kitti_odometry" / "sequences" / "06"
    if not seq_dir.is_dir():
        pytest.skip(f"{seq_dir} is absent")
    return KittiOdometry(seq_dir, shared_data / "kitti_odometry" / "poses" / "06.txt")


FRAMES = list(range(0, 42, 3))  # 14 keyframes, ~1.2 m apart at the start


@pytest.fixture(scope="module")
def kitti06_keyframes(kitti06):
    """(frame, landmark pixels, inverse depths) of the database keyframes, computed once."""
    out = []
    for i in FRAMES:
        f = kitti06[i]
        out.append((f, *_landmarks(f)))
    return out


@pytest.mark.slow
def test_revisit_detected_with_correct_sim3(kitti06, kitti06_keyframes):
    det = LoopDetector(CONFIG)
    frames = FRAMES
    for kf_id, (f, uv, xi) in enumerate(kitti06_keyframes):
        assert det.add_and_query(kf_id, f.image, f.camera, uv, xi) == []  # nothing old enough
    q = kitti06[1]  # back near the start
    uv, xi = _landmarks(q)
    loops = det.add_and_query(len(frames), q.image, q.camera, uv, xi)
    assert len(loops) == 1
    loop = loops[0]
    assert frames[loop.kf_old] in (0, 3)
    T_gt = se3.inverse(kitti06.T_world_cam_gt[frames[loop.kf_old]]) @ kitti06.T_world_cam_gt[1]
    R, t, s = sim3.split(loop.S_old_new)
    assert s == pytest.approx(1.0, abs=0.1)  # both sides metric (stereo)
    assert np.linalg.norm(t - T_gt[:3, 3]) < 0.35
    assert np.degrees(np.linalg.norm(cv2.Rodrigues(R.T @ T_gt[:3, :3])[0])) < 1.5


@pytest.mark.slow
def test_new_place_is_not_a_loop(kitti06_keyframes, shared_data):
    from metricslam.datasets.kitti import KittiOdometry

    det = LoopDetector(CONFIG)
    for kf_id, (f, uv, xi) in enumerate(kitti06_keyframes):
        det.add_and_query(kf_id, f.image, f.camera, uv, xi)
    seq01 = shared_data / "kitti_odometry" / "sequences" / "01"
    if not seq01.is_dir():
        pytest.skip(f"{seq01} is absent")
    other = KittiOdometry(seq01)
    for j, i in enumerate((0, 20, 40)):  # a highway: never seen before
        f = other[i]
        assert det.add_and_query(100 + j, f.image, f.camera, *_landmarks(f)) == []
