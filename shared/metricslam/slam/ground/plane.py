"""Road-plane geometry: the plane-induced warp between two views and the road region.

Frames and units follow ``docs/conventions.md``: camera x right, y down, z forward;
``T_prev_cur`` maps a point of the current keyframe's camera frame into the previous one's.
The road plane is written in the current camera frame as ``n_cur · X_cur = h`` with ``n_cur``
the unit normal pointing **down** (towards the road, +y for a level camera) and ``h > 0`` the
camera's height above the road in the units of ``T_prev_cur``'s translation (VO units in the
SLAM system, metres with a metric pose).
"""

from __future__ import annotations

import math

import numpy as np

from metricslam.errors import ScaleError


def nominal_down(pitch_rad: float = 0.0) -> np.ndarray:
    """(3,) unit "down" direction in the camera frame for a camera pitched by ``pitch_rad``
    (positive = optical axis tilted towards the road; 0 = level, down = +y)."""
    return np.array([0.0, np.cos(pitch_rad), np.sin(pitch_rad)])


def tilt_normal(n0: np.ndarray, tilt_rad: np.ndarray) -> np.ndarray:
    """(3,) ``n0`` rotated by ``Exp([tilt_x, 0, tilt_z])`` (pitch about x, roll about z).

    Scalar arithmetic (Rodrigues' formula written out): the road aligner calls it a hundred
    times per keyframe, and ``np.cross`` on 3-vectors costs more than the whole rotation."""
    wx, wz = float(tilt_rad[0]), float(tilt_rad[1])
    a, b, c = (float(v) for v in n0)
    th = math.hypot(wx, wz)
    if th < 1e-12:
        return np.array([a, b, c])
    kx, kz = wx / th, wz / th
    cos_t, sin_t = math.cos(th), math.sin(th)
    k_dot_n = (kx * a + kz * c) * (1.0 - cos_t)
    # k × n0 with k = (kx, 0, kz)
    return np.array([a * cos_t - kz * b * sin_t + kx * k_dot_n,
                     b * cos_t + (kz * a - kx * c) * sin_t,
                     c * cos_t + kx * b * sin_t + kz * k_dot_n])


def tilt_normal_derivatives(n0: np.ndarray, tilt_rad: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """(3, 3) columns ``[n, ∂n/∂tilt_x, ∂n/∂tilt_z]`` at ``tilt_rad`` (central differences,
    step ``eps`` rad; checked against the warp's finite differences in tests)."""
    tx, tz = float(tilt_rad[0]), float(tilt_rad[1])
    cols = [tilt_normal(n0, (tx, tz)),
            (tilt_normal(n0, (tx + eps, tz)) - tilt_normal(n0, (tx - eps, tz))) / (2 * eps),
            (tilt_normal(n0, (tx, tz + eps)) - tilt_normal(n0, (tx, tz - eps))) / (2 * eps)]
    return np.stack(cols, axis=1)


def road_rays(K: np.ndarray, width_px: int, height_px: int, n_down: np.ndarray,
              lateral_half_width: float, forward_range: tuple[float, float],
              min_below_horizon_px: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of the expected road patch ahead of the camera and their rays.

    The patch is scale-free: a ground point ``X = h·r / (n·r)`` is kept when its lateral
    offset is within ``lateral_half_width·h`` and its forward distance within
    ``forward_range·h`` (e.g. ±1.2 h and 3–12 h: a lane ahead, away from kerbs and parked cars).

    Args:
        K: (3, 3) intrinsics (pixel centres at integers).
        width_px, height_px: image size.
        n_down: (3,) expected unit plane normal (down) in the camera frame.
    Returns:
        ``(uv_px (N, 2) float32, rays (N, 3))`` with ``rays = K⁻¹ [u, v, 1]``; N may be 0.
    """
    v, u = np.mgrid[0:height_px, 0:width_px]
    uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(float)
    rays = np.linalg.solve(K, np.vstack([uv.T, np.ones(len(uv))])).T
    cos_down = rays @ n_down
    # a few pixels below the horizon at least: near the horizon the plane point runs off to infinity
    below = cos_down > min_below_horizon_px / float(K[1, 1])
    X = rays[below] / cos_down[below, None]  # ground point for h = 1
    fwd = np.cross(np.array([1.0, 0.0, 0.0]), n_down)  # forward along the road (z for level)
    lat = np.cross(n_down, fwd)  # right along the road
    keep = ((np.abs(X @ lat) <= lateral_half_width)
            & (X @ fwd >= forward_range[0]) & (X @ fwd <= forward_range[1]))
    idx = np.flatnonzero(below)[keep]
    return uv[idx].astype(np.float32), rays[idx]


def warp_to_prev(rays_cur: np.ndarray, K: np.ndarray, T_prev_cur: np.ndarray, n_cur: np.ndarray,
                 h: float) -> tuple[np.ndarray, np.ndarray]:
    """Where the road point seen along each current ray lands in the previous image.

    Args:
        rays_cur: (N, 3) rays ``K⁻¹ [u, v, 1]`` of current-image pixels.
        K: (3, 3) intrinsics of both images.
        T_prev_cur: (4, 4) current camera in the previous one (units of ``h``).
        n_cur: (3,) unit plane normal (down) in the current frame; ``h`` > 0 the height.
    Returns:
        ``(uv_prev_px (N, 2), z_prev (N,))``: pixels in the previous image and the points' depth
        there (≤ 0: behind the previous camera).
    """
    if h <= 0 or not np.isfinite(h):
        raise ScaleError(f"plane height must be a positive finite number, got {h}")
    X_cur = rays_cur * (h / (rays_cur @ n_cur))[:, None]
    X_prev = X_cur @ T_prev_cur[:3, :3].T + T_prev_cur[:3, 3]
    p = X_prev @ K.T
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = p[:, :2] / z[:, None]
    return uv, z


def plane_homography(K: np.ndarray, T_prev_cur: np.ndarray, n_cur: np.ndarray, h: float) -> np.ndarray:
    """(3, 3) homography ``H_prev_cur = K (R + t nᵀ / h) K⁻¹`` induced by the road plane
    ``n_cur · X = h`` (maps current pixels to previous pixels, homogeneous)."""
    R, t = T_prev_cur[:3, :3], T_prev_cur[:3, 3]
    return K @ (R + np.outer(t, n_cur) / float(h)) @ np.linalg.inv(K)
