"""Stereo block matching on rectified pairs (OpenCV SGBM), left-right checked.

One matcher for everything that needs stereo disparity: the depth network's training labels
(``metricslam_train.data``), the depth benchmark's KITTI reference (``bench/depth_accuracy.py``)
and the stereo upper bound / pair check (``bench/scale_upper_bound.py``), so a check of the pair
measures the same disparities the labels were made from.
"""

from __future__ import annotations

import cv2
import numpy as np


def sgbm_matcher(num_disparities: int = 128, block_size: int = 5) -> cv2.StereoSGBM:
    """OpenCV semi-global block matcher with settings that suit KITTI-like street scenes."""
    return cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=num_disparities, blockSize=block_size,
        P1=8 * block_size * block_size, P2=32 * block_size * block_size, disp12MaxDiff=1,
        uniquenessRatio=10, speckleWindowSize=100, speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )


def block_matching_pair(left: np.ndarray, right: np.ndarray, num_disparities: int = 128,
                        lr_tol_px: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Full-resolution SGBM disparities (px, float32, 0 = invalid) for the left and right images.

    The right map comes from the mirrored, swapped pair; both are cross-checked
    (``|d_l(u) − d_r(u − d_l(u))| ≤ lr_tol_px``).
    """
    matcher = sgbm_matcher(num_disparities)
    d_left = matcher.compute(left, right).astype(np.float32) / 16.0
    d_right = matcher.compute(right[:, ::-1].copy(), left[:, ::-1].copy()).astype(np.float32)[:, ::-1] / 16.0
    d_left[d_left <= 0] = 0
    d_right[d_right <= 0] = 0
    h, w = left.shape
    cols = np.arange(w)[None, :].repeat(h, 0)
    rows = np.arange(h)[:, None].repeat(w, 1)
    u_r = np.clip(np.round(cols - d_left).astype(int), 0, w - 1)
    ok_l = (d_left > 0) & (np.abs(d_left - d_right[rows, u_r]) <= lr_tol_px)
    u_l = np.clip(np.round(cols + d_right).astype(int), 0, w - 1)
    ok_r = (d_right > 0) & (np.abs(d_right - d_left[rows, u_l]) <= lr_tol_px)
    return np.where(ok_l, d_left, 0).astype(np.float32), np.where(ok_r, d_right, 0).astype(np.float32)
