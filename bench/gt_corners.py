"""Corners tracked with KLT and triangulated with a known (ground-truth) motion: the reference
depth of the depth benches (``landmark_depth.py``, ``scale_upper_bound.py``'s stereo check).

EVALUATION ONLY: the motion comes from the ground truth, never from the system under test.
"""

from __future__ import annotations

import cv2
import numpy as np

_LK = {"winSize": (21, 21), "maxLevel": 3, "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}

def intrinsics(camera) -> np.ndarray:
    """(3, 3) K of a :class:`~metricslam.camera.PinholeCamera` (pixels)."""
    return np.array([[camera.fx_px, 0.0, camera.cx_px], [0.0, camera.fy_px, camera.cy_px], [0.0, 0.0, 1.0]])


def track_corners(images: list[np.ndarray], max_corners: int = 1000, quality: float = 0.01,
                  min_distance_px: float = 7.0, fb_max_px: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Corners of ``images[0]`` tracked frame to frame through ``images[1:]`` (pyramidal KLT, each
    step forward-backward checked to ``fb_max_px``); a corner lost at some step keeps its last
    good position.

    Returns:
        ``(uv_0, uv_last, steps)``: (N, 2) float64 pixels (u, v) in ``images[0]`` and in
        ``images[steps]``, and (N,) int ``steps`` ≥ 1 (corners lost at the first step are dropped).
    """
    p0 = cv2.goodFeaturesToTrack(images[0], max_corners, quality, min_distance_px)
    if p0 is None or len(images) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, int)
    p0 = p0.reshape(-1, 1, 2).astype(np.float32)
    cur = p0.copy()
    steps = np.zeros(len(p0), int)
    alive = np.ones(len(p0), bool)
    for k in range(1, len(images)):
        idx = np.nonzero(alive)[0]
        if idx.size == 0:
            break
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(images[k - 1], images[k], cur[idx], None, **_LK)
        back, st_b, _ = cv2.calcOpticalFlowPyrLK(images[k], images[k - 1], nxt, None, **_LK)
        h, w = images[k].shape[:2]
        u, v = nxt[:, 0, 0], nxt[:, 0, 1]
        ok = ((st[:, 0] == 1) & (st_b[:, 0] == 1) & (np.linalg.norm((back - cur[idx])[:, 0], axis=1) < fb_max_px)
              & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1))
        alive[idx[~ok]] = False
        cur[idx[ok]] = nxt[ok]
        steps[idx[ok]] = k
    got = steps >= 1
    return p0[got, 0].astype(np.float64), cur[got, 0].astype(np.float64), steps[got]


def triangulate_gt(uv_a: np.ndarray, uv_b: np.ndarray, K: np.ndarray, T_b_a: np.ndarray,
                   max_reproj_px: float = 1.0, depth_range_m: tuple[float, float] = (2.0, 60.0),
                   min_parallax_deg: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate tracks with a known (ground-truth) relative motion.

    Args:
        uv_a, uv_b: (N, 2) pixels of the same points in frames a and b.
        K: (3, 3) intrinsics (both frames).
        T_b_a: (4, 4) pose of camera a in camera b (``inv(T_world_b) @ T_world_a``), metres.
        max_reproj_px: largest reprojection error accepted in either frame.
        depth_range_m: accepted depth in frame a (m).
        min_parallax_deg: smallest angle between the two viewing rays.

    Returns:
        ``(keep, z_a)``: (N,) bool mask of accepted points and (N,) depth in frame a (m; every
        point, accepted or not).
    """
    n = len(uv_a)
    if n == 0:
        return np.zeros(0, bool), np.zeros(0)
    P_a = K @ np.eye(3, 4)
    P_b = K @ T_b_a[:3]
    X_h = cv2.triangulatePoints(P_a, P_b, uv_a.T.astype(np.float64), uv_b.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        X = (X_h[:3] / X_h[3]).T  # (N, 3) in frame a
        X_b = X @ T_b_a[:3, :3].T + T_b_a[:3, 3]
        err_a = np.linalg.norm(X @ K.T[:, :2] / (X @ K.T[:, 2:]) - uv_a, axis=1)
        err_b = np.linalg.norm(X_b @ K.T[:, :2] / (X_b @ K.T[:, 2:]) - uv_b, axis=1)
        ray_a = X / np.linalg.norm(X, axis=1, keepdims=True)
        ray_b = X_b / np.linalg.norm(X_b, axis=1, keepdims=True) @ T_b_a[:3, :3]  # b's ray in frame a
        parallax = np.degrees(np.arccos(np.clip(np.sum(ray_a * ray_b, axis=1), -1.0, 1.0)))
    z = X[:, 2]
    keep = (np.isfinite(z) & (X_b[:, 2] > 0) & (z >= depth_range_m[0]) & (z <= depth_range_m[1])
            & (err_a < max_reproj_px) & (err_b < max_reproj_px) & (parallax >= min_parallax_deg))
    return keep, z
