"""The camera's height above the road between two keyframes, from a dense plane-induced warp.

Given two gray images and the relative pose between them (``T_prev_cur``, VO units), the road
patch ahead of the current camera (:func:`~.plane.road_rays`) is warped into the previous image
through the plane ``n_cur · X = h`` and the photometric residual is minimized over
``p = [log h, tilt_x, tilt_z]`` (height and the normal's pitch and roll) — direct image
alignment, coarse to fine on an image pyramid, with an affine brightness fit, a Huber kernel on
the residuals (cars, shadows, kerbs) and a 1-D search over ``log(h/|t|)`` at the coarsest level
to start. The result is in the units of ``T_prev_cur``'s translation, so with a VO pose it is the
road height in keyframe units (``h_vo``) and ``h_mount_m / h_vo`` is a metric scale measurement.

A measurement is accepted only when the patch is road-like: enough textured pixels, enough of
them explained by the plane (inlier fraction), a normal within ``max_normal_deg`` of the
expected down direction, enough motion relative to the height, and a small log-height
uncertainty. See docs/ground_scale.md; frames and units: docs/conventions.md.

Example::

    res = estimate_ground_height(img_prev, img_cur, camera.K, T_prev_cur, GroundHeightConfig())
    if res.accepted:
        scale_m_per_unit = 1.65 / res.height
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from metricslam.errors import ScaleError
from metricslam.slam.ground.plane import nominal_down, road_rays, tilt_normal


class GroundHeightConfig(BaseModel):
    """Parameters of the road-height estimator (chosen on rendered streets and raw 0013;
    ``bench/ground_scale.py``).

    Attributes:
        pitch_rad: nominal camera pitch (optical axis towards the road is positive).
        lateral_half_width: half width of the road patch, in camera heights (1.2 h ≈ ±2 m).
        forward_min / forward_max: its forward extent, in camera heights.
        levels: image pyramid levels (coarsest first is ``levels - 1``); ``finest_level`` the
            last one aligned (1 = half resolution: enough texture, a quarter of the cost).
        min_gradient: pixels whose image gradient (gray levels / px at their level) is below
            this carry no information and are skipped.
        max_pixels: at most this many pixels per level (an even subsample).
        grid_min / grid_max / grid_steps: the initial search over ``h / |t|``.
        iterations: Gauss-Newton iterations per level.
        huber_k: Huber threshold on residuals in robust standard deviations (MAD).
        inlier_gray: a pixel is an inlier when its residual is below this (gray levels).
        min_pixels, min_inlier_fraction, max_normal_deg, max_sigma_log, min_motion_over_h:
            the acceptance gates (module docstring).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    pitch_rad: float = 0.0
    lateral_half_width: float = Field(default=1.2, gt=0)
    forward_min: float = Field(default=3.0, gt=0)
    forward_max: float = Field(default=12.0, gt=0)
    levels: int = Field(default=3, ge=1, le=5)
    finest_level: int = Field(default=0, ge=0)
    min_gradient: float = Field(default=2.0, ge=0)
    max_pixels: int = Field(default=8000, gt=100)
    grid_min: float = Field(default=0.2, gt=0)
    grid_max: float = Field(default=10.0, gt=0)
    grid_steps: int = Field(default=24, ge=4)
    iterations: int = Field(default=8, ge=1)
    huber_k: float = Field(default=1.345, gt=0)
    inlier_gray: float = Field(default=10.0, gt=0)
    min_pixels: int = Field(default=400, ge=10)
    min_inlier_fraction: float = Field(default=0.5, ge=0, le=1)
    max_normal_deg: float = Field(default=8.0, gt=0)
    max_sigma_log: float = Field(default=0.03, gt=0)
    min_motion_over_h: float = Field(default=0.15, gt=0)


@dataclass(frozen=True)
class GroundHeight:
    """One road-height measurement of the current keyframe.

    Attributes:
        height: camera height above the road plane, units of ``T_prev_cur``'s translation
            (NaN when no estimate was made).
        n_cur: (3,) unit road normal (down) in the current camera frame.
        sigma_log: standard deviation of ``log height`` from the final Gauss-Newton system.
        n_pixels: pixels used at the finest level.
        inlier_fraction: share of them with a residual below ``inlier_gray``.
        normal_angle_rad: angle between ``n_cur`` and the nominal down direction.
        accepted: all gates passed; ``reason`` says which failed otherwise.
    """

    height: float
    n_cur: np.ndarray
    sigma_log: float
    n_pixels: int
    inlier_fraction: float
    normal_angle_rad: float
    accepted: bool
    reason: str = ""


def _pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    out = [np.asarray(img, dtype=np.float32)]
    for _ in range(levels - 1):
        out.append(cv2.pyrDown(out[-1]))
    return out


def _level_K(K: np.ndarray, level: int) -> np.ndarray:
    """Intrinsics at pyramid ``level`` (pixel centres at integers: u_L = (u + 0.5)/2^L − 0.5)."""
    f = 0.5 ** level
    K_L = np.array(K, dtype=float)
    K_L[0, 0] *= f
    K_L[1, 1] *= f
    K_L[0, 2] = (K[0, 2] + 0.5) * f - 0.5
    K_L[1, 2] = (K[1, 2] + 0.5) * f - 0.5
    return K_L


class _Level:
    """Pixels, rays and images of one pyramid level."""

    def __init__(self, prev: np.ndarray, cur: np.ndarray, K: np.ndarray,
                 region: tuple[np.ndarray, np.ndarray], cfg: GroundHeightConfig) -> None:
        self.K = K
        self.prev = prev
        self.gx = cv2.Sobel(prev, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        self.gy = cv2.Sobel(prev, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        uv, rays = region
        if len(uv):
            gcx = cv2.Sobel(cur, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
            gcy = cv2.Sobel(cur, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
            ui, vi = uv[:, 0].astype(int), uv[:, 1].astype(int)
            textured = np.hypot(gcx[vi, ui], gcy[vi, ui]) >= cfg.min_gradient
            uv, rays = uv[textured], rays[textured]
        if len(uv) > cfg.max_pixels:
            idx = np.linspace(0, len(uv) - 1, cfg.max_pixels).round().astype(int)
            uv, rays = uv[idx], rays[idx]
        self.rays = rays
        ui, vi = uv[:, 0].astype(int), uv[:, 1].astype(int)
        self.i_cur = cur[vi, ui].astype(float)

    def sample(self, img: np.ndarray, uv: np.ndarray) -> np.ndarray:
        m = uv.astype(np.float32).reshape(-1, 1, 2)
        return cv2.remap(img, m, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=np.nan).reshape(-1).astype(float)

    def residuals(self, T_prev_cur: np.ndarray, n0: np.ndarray, p: np.ndarray,
                  with_jacobian: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, float]:
        """Residuals (N,) (NaN where the warp leaves the image), their Jacobian (N, 3) w.r.t.
        ``p`` (optional), the valid mask and the brightness gain."""
        uv, A_z, duv = plane_warp(self.rays, self.K, T_prev_cur, n0, p, with_jacobian)
        iw = self.sample(self.prev, uv)
        valid = np.isfinite(iw) & (A_z > 0)
        if valid.sum() < 10:
            return np.full(len(iw), np.nan), None, valid, 1.0
        x, y = iw[valid], self.i_cur[valid]
        x_c = x - x.mean()
        gain = float(x_c @ (y - y.mean()) / max(float(x_c @ x_c), 1e-9))
        bias = float(y.mean() - gain * x.mean())
        r = np.full(len(iw), np.nan)
        r[valid] = gain * iw[valid] + bias - self.i_cur[valid]
        if not with_jacobian:
            return r, None, valid, float(gain)
        gx, gy = self.sample(self.gx, uv), self.sample(self.gy, uv)
        J = gain * (gx[:, None] * duv[:, 0, :] + gy[:, None] * duv[:, 1, :])
        valid &= np.all(np.isfinite(J), axis=1)
        return r, J, valid, float(gain)


def plane_warp(rays: np.ndarray, K: np.ndarray, T_prev_cur: np.ndarray, n0: np.ndarray, p: np.ndarray,
               with_jacobian: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Previous-image pixels of the road points on ``rays`` (N, 3) for ``p = [log h, tilt_x,
    tilt_z]`` (plane ``n · X = h``, ``n = tilt_normal(n0, tilt)``, current camera frame).

    Returns:
        ``(uv_prev_px (N, 2), A_z (N,), duv_dp (N, 2, 3) or None)``: ``A_z > 0`` iff the point is
        in front of the previous camera; ``duv_dp`` the warp's Jacobian (tested against central
        differences of :func:`~.plane.warp_to_prev`).
    """
    h = float(np.exp(p[0]))
    n = tilt_normal(n0, p[1:])
    # homogeneous previous-image point of the plane point on each ray: K (R q + t (n·q) / h),
    # the ray's plane point h q / (n·q) scaled by (n·q) / h > 0
    c = (rays @ n) / h
    Kt = K @ T_prev_cur[:3, 3]
    A = rays @ (K @ T_prev_cur[:3, :3]).T + c[:, None] * Kt[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = A[:, :2] / A[:, 2:3]
    if not with_jacobian:
        return uv, A[:, 2], None
    # dA/dp_k = dc_k · K t with dc/dlog h = −c and dc/dtilt_k = (q · ∂n/∂tilt_k) / h
    eps = 1e-6
    dc = [-c]
    for k in range(2):
        d = np.zeros(2)
        d[k] = eps
        dn = (tilt_normal(n0, p[1:] + d) - tilt_normal(n0, p[1:] - d)) / (2 * eps)
        dc.append((rays @ dn) / h)
    duv = np.empty((len(rays), 2, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            duv[:, 0, k] = dc[k] * (Kt[0] - uv[:, 0] * Kt[2]) / A[:, 2]
            duv[:, 1, k] = dc[k] * (Kt[1] - uv[:, 1] * Kt[2]) / A[:, 2]
    return uv, A[:, 2], duv


def _robust_sigma(r: np.ndarray) -> float:
    return max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1.0)


def _huber_weights(r: np.ndarray, sigma: float, k: float) -> np.ndarray:
    a = np.abs(r) / sigma
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def _grid_start(level: _Level, T_prev_cur: np.ndarray, n0: np.ndarray, t_norm: float,
                cfg: GroundHeightConfig) -> float:
    """``log h`` of the best plane height on a log grid (median absolute residual)."""
    best, best_cost = np.log(t_norm * np.sqrt(cfg.grid_min * cfg.grid_max)), np.inf
    for ratio in np.geomspace(cfg.grid_min, cfg.grid_max, cfg.grid_steps):
        p = np.array([np.log(t_norm * ratio), 0.0, 0.0])
        r, _, valid, _ = level.residuals(T_prev_cur, n0, p, with_jacobian=False)
        if valid.sum() < 0.5 * len(r) or valid.sum() < 10:
            continue
        cost = float(np.median(np.abs(r[valid])))
        if cost < best_cost:
            best, best_cost = float(p[0]), cost
    return best


def _rejected(reason: str, n0: np.ndarray, h: float = float("nan"), **kw: float) -> GroundHeight:
    return GroundHeight(h, n0, kw.get("sigma_log", float("inf")), int(kw.get("n_pixels", 0)),
                        kw.get("inlier_fraction", 0.0), kw.get("normal_angle_rad", 0.0), False, reason)


def estimate_ground_height(img_prev: np.ndarray, img_cur: np.ndarray, K: np.ndarray,
                           T_prev_cur: np.ndarray,
                           config: GroundHeightConfig | None = None) -> GroundHeight:
    """One-off :meth:`RoadHeightEstimator.estimate` (module docstring)."""
    return RoadHeightEstimator(config).estimate(img_prev, img_cur, K, T_prev_cur)


class RoadHeightEstimator:
    """:func:`estimate_ground_height` that keeps the road region of each image size and camera
    (the rays of the patch cost more than the alignment; a SLAM run has one camera).

    Args:
        config: parameters (default :class:`GroundHeightConfig`).
    """

    def __init__(self, config: GroundHeightConfig | None = None) -> None:
        self.config = config or GroundHeightConfig()
        self._regions: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def _region(self, K_L: np.ndarray, shape: tuple[int, int], n0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = (shape, K_L.tobytes())
        if key not in self._regions:
            if len(self._regions) > 16:  # a new camera: forget the old one's
                self._regions.clear()
            cfg = self.config
            self._regions[key] = road_rays(K_L, shape[1], shape[0], n0, cfg.lateral_half_width,
                                           (cfg.forward_min, cfg.forward_max))
        return self._regions[key]

    def estimate(self, img_prev: np.ndarray, img_cur: np.ndarray, K: np.ndarray,
                 T_prev_cur: np.ndarray) -> GroundHeight:
        """The current camera's height above the road plane (module docstring).

        Args:
            img_prev, img_cur: (H, W) gray images (uint8 or float) of the previous and current
                keyframe, same camera.
            K: (3, 3) intrinsics.
            T_prev_cur: (4, 4) current camera pose in the previous camera's frame.
        Returns:
            A :class:`GroundHeight`; ``accepted`` False (with a reason) when the road is not usable.
        """
        cfg = self.config
        if img_prev.shape != img_cur.shape or img_cur.ndim != 2:
            raise ScaleError(f"ground height needs two gray images of one size, got {img_prev.shape} "
                             f"and {img_cur.shape}")
        T_prev_cur = np.asarray(T_prev_cur, dtype=float)
        n0 = nominal_down(cfg.pitch_rad)
        t_norm = float(np.linalg.norm(T_prev_cur[:3, 3]))
        if not np.isfinite(t_norm) or t_norm < 1e-9:
            return _rejected("no motion between the keyframes", n0)
        pyr_prev, pyr_cur = _pyramid(img_prev, cfg.levels), _pyramid(img_cur, cfg.levels)
        p = None
        last = None
        for lv in range(cfg.levels - 1, min(cfg.finest_level, cfg.levels - 1) - 1, -1):
            K_L = _level_K(K, lv)
            region = self._region(K_L, pyr_cur[lv].shape, n0)
            level = _Level(pyr_prev[lv], pyr_cur[lv], K_L, region, cfg)
            if len(level.rays) < 10:
                return _rejected("no textured road region below the horizon", n0, n_pixels=len(level.rays))
            if p is None:
                p = np.array([_grid_start(level, T_prev_cur, n0, t_norm, cfg), 0.0, 0.0])
            for _ in range(cfg.iterations):
                r, J, valid, _ = level.residuals(T_prev_cur, n0, p, with_jacobian=True)
                if J is None or valid.sum() < 10:
                    break
                rv, Jv = r[valid], J[valid]
                w = _huber_weights(rv, _robust_sigma(rv), cfg.huber_k)
                H = (Jv * w[:, None]).T @ Jv
                g = (Jv * w[:, None]).T @ rv
                try:
                    dp = -np.linalg.solve(H + 1e-6 * np.trace(H) * np.eye(3), g)
                except np.linalg.LinAlgError:
                    break
                dp = np.clip(dp, -0.3, 0.3)
                p = p + dp
                if np.max(np.abs(dp)) < 1e-4:
                    break
            last = level
        r, J, valid, _ = last.residuals(T_prev_cur, n0, p, with_jacobian=True)
        n_cur = tilt_normal(n0, p[1:])
        h = float(np.exp(p[0]))
        angle = float(np.arccos(np.clip(n_cur @ n0, -1.0, 1.0)))
        n_valid = int(valid.sum())
        if J is None or n_valid < cfg.min_pixels:
            return _rejected(f"too few road pixels ({n_valid} < {cfg.min_pixels})", n_cur, h,
                             n_pixels=n_valid, normal_angle_rad=angle)
        rv, Jv = r[valid], J[valid]
        sigma_r = _robust_sigma(rv)
        w = _huber_weights(rv, sigma_r, cfg.huber_k)
        try:
            cov = sigma_r ** 2 * np.linalg.inv((Jv * w[:, None]).T @ Jv)
            sigma_log = float(np.sqrt(max(cov[0, 0], 0.0)))
        except np.linalg.LinAlgError:
            sigma_log = float("inf")
        inliers = float(np.mean(np.abs(rv) < cfg.inlier_gray))
        stats = dict(sigma_log=sigma_log, n_pixels=n_valid, inlier_fraction=inliers, normal_angle_rad=angle)
        if t_norm / h < cfg.min_motion_over_h:
            return _rejected(f"too little motion for the height (|t|/h = {t_norm / h:.3f})", n_cur, h, **stats)
        if inliers < cfg.min_inlier_fraction:
            return _rejected(f"the plane explains only {100 * inliers:.0f} % of the road pixels", n_cur, h, **stats)
        if np.degrees(angle) > cfg.max_normal_deg:
            return _rejected(f"road normal {np.degrees(angle):.1f} deg from down", n_cur, h, **stats)
        if not sigma_log <= cfg.max_sigma_log:
            return _rejected(f"height too uncertain (sigma log {sigma_log:.3f})", n_cur, h, **stats)
        return GroundHeight(h, n_cur, sigma_log, n_valid, inliers, angle, True)
