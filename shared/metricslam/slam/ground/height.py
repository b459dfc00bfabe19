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

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from metricslam.errors import ScaleError
from metricslam.slam.ground.plane import nominal_down, tilt_normal, tilt_normal_derivatives
from metricslam.slam.ground.road_image import (RoadImage, RoadPatch, RoadRegion, level_K, prepare_road_image,
                                               road_region)


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
        grid_min / grid_max / grid_steps: the initial search over ``h / |t|``; ``grid_pixels``
            the most pixels it uses (an even subsample: it only picks the start; 1,000 gave the
            same starts and accept decisions as all ~2,000 on raw 0013).
        iterations: Gauss-Newton iterations per level; a level stops early once no parameter
            steps more than ``step_tolerance`` (1e-3: 0.1 % of the height, a tenth of one
            keyframe's height noise; 1e-4 cost a fifth more time for changes under 0.2 %).
        huber_k: Huber threshold on residuals in robust standard deviations (MAD);
            ``mad_samples`` the most residuals the MAD is taken over (an even subsample; 2,000 pin
            it to ~3 %; the MAD over all 8,000 was the aligner's largest cost).
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
    grid_pixels: int = Field(default=1000, ge=10)
    iterations: int = Field(default=8, ge=1)
    step_tolerance: float = Field(default=1e-3, gt=0)
    huber_k: float = Field(default=1.345, gt=0)
    mad_samples: int = Field(default=2000, ge=10)
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
    dn = tilt_normal_derivatives(n0, p[1:])
    dc = [-c, (rays @ dn[:, 1]) / h, (rays @ dn[:, 2]) / h]
    duv = np.empty((len(rays), 2, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            duv[:, 0, k] = dc[k] * (Kt[0] - uv[:, 0] * Kt[2]) / A[:, 2]
            duv[:, 1, k] = dc[k] * (Kt[1] - uv[:, 1] * Kt[2]) / A[:, 2]
    return uv, A[:, 2], duv


_EYE3 = np.eye(3)


def _median(x: np.ndarray) -> float:
    """``np.median`` of a finite 1-D array, without its NaN pass (the aligner's hot loop)."""
    k = len(x) // 2
    if len(x) % 2:
        return float(np.partition(x, k)[k])
    part = np.partition(x, (k - 1, k))
    return float(0.5 * (part[k - 1] + part[k]))


def _robust_sigma(r: np.ndarray, max_samples: int) -> float:
    """1.4826 · MAD of the residuals (gray levels), at least 1; over an even subsample of at
    most ``max_samples`` of them (``GroundHeightConfig.mad_samples``)."""
    step = -(-len(r) // max_samples)
    if step > 1:
        r = r[::step]
    return max(1.4826 * _median(np.abs(r - _median(r))), 1.0)


def _huber_weights(r: np.ndarray, sigma: float, k: float) -> np.ndarray:
    a = np.abs(r) / sigma
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def _grid_start(patch: RoadPatch, t_norm: float, cfg: GroundHeightConfig) -> float:
    """``log h`` of the best level-plane height on a log grid of ``h / |t|`` (median absolute
    residual; the first of equal ones; the grid's middle when none warps validly)."""
    heights = t_norm * np.geomspace(cfg.grid_min, cfg.grid_max, cfg.grid_steps)
    costs = patch.grid_costs(heights, cfg.grid_pixels)
    if not np.isfinite(costs).any():
        return float(np.log(t_norm * np.sqrt(cfg.grid_min * cfg.grid_max)))
    return float(np.log(heights[int(np.argmin(costs))]))


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

    A caller that measures a chain of keyframes prepares each image once
    (:meth:`prepare`) and calls :meth:`estimate_prepared`: the current image of one measurement is
    the previous one of the next.

    Args:
        config: parameters (default :class:`GroundHeightConfig`).
    """

    def __init__(self, config: GroundHeightConfig | None = None) -> None:
        self.config = config or GroundHeightConfig()
        self._regions: dict[tuple, RoadRegion] = {}

    def _region(self, K_L: np.ndarray, shape: tuple[int, int], n0: np.ndarray) -> RoadRegion:
        key = (shape, K_L.tobytes())
        if key not in self._regions:
            if len(self._regions) > 16:  # a new camera: forget the old one's
                self._regions.clear()
            cfg = self.config
            self._regions[key] = road_region(K_L, shape, n0, cfg.lateral_half_width,
                                             (cfg.forward_min, cfg.forward_max))
        return self._regions[key]

    def prepare(self, img: np.ndarray) -> RoadImage:
        """(H, W) gray image (uint8 or float) → its :class:`~.road_image.RoadImage`."""
        img = np.asarray(img)
        if img.ndim != 2:
            raise ScaleError(f"ground height needs a gray (H, W) image, got shape {img.shape}")
        return prepare_road_image(img, self.config.levels, min(self.config.finest_level, self.config.levels - 1))

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
        if img_prev.shape != img_cur.shape or img_cur.ndim != 2:
            raise ScaleError(f"ground height needs two gray images of one size, got {img_prev.shape} "
                             f"and {img_cur.shape}")
        return self.estimate_prepared(self.prepare(img_prev), self.prepare(img_cur), K, T_prev_cur)

    def estimate_prepared(self, prev: RoadImage, cur: RoadImage, K: np.ndarray,
                          T_prev_cur: np.ndarray) -> GroundHeight:
        """:meth:`estimate` on images already prepared by :meth:`prepare` (same arguments)."""
        cfg = self.config
        if prev.shape != cur.shape or len(prev.levels) != cfg.levels or len(cur.levels) != cfg.levels:
            raise ScaleError(f"ground height needs two images of one size prepared for {cfg.levels} "
                             f"levels, got {prev.shape} and {cur.shape}")
        T_prev_cur = np.asarray(T_prev_cur, dtype=float)
        n0 = nominal_down(cfg.pitch_rad)
        t_norm = float(np.linalg.norm(T_prev_cur[:3, 3]))
        if not np.isfinite(t_norm) or t_norm < 1e-9:
            return _rejected("no motion between the keyframes", n0)
        p = None
        patch = None
        finest = min(cfg.finest_level, cfg.levels - 1)
        for lv in range(cfg.levels - 1, finest - 1, -1):
            K_L = level_K(K, lv)
            shape = cur.levels[lv].shape[:2]
            patch = RoadPatch(prev.levels[lv], cur.levels[lv], K_L, self._region(K_L, shape, n0),
                              T_prev_cur, n0, cfg.min_gradient, cfg.max_pixels)
            if len(patch) < 10:
                return _rejected("no textured road region below the horizon", n0, n_pixels=len(patch))
            if p is None:
                p = np.array([_grid_start(patch, t_norm, cfg), 0.0, 0.0])
            for _ in range(cfg.iterations):
                rv, Jt = patch.residuals(p, with_jacobian=True)
                if Jt is None:
                    break
                Jw = Jt * _huber_weights(rv, _robust_sigma(rv, cfg.mad_samples), cfg.huber_k)
                H = Jw @ Jt.T
                g = Jw @ rv
                try:
                    dp = -np.linalg.solve(H + 1e-6 * np.trace(H) * _EYE3, g)
                except np.linalg.LinAlgError:
                    break
                dp = np.clip(dp, -0.3, 0.3)
                p = p + dp
                if np.max(np.abs(dp)) < cfg.step_tolerance:
                    break
        rv, Jt = patch.residuals(p, with_jacobian=True)
        n_cur = tilt_normal(n0, p[1:])
        h = float(np.exp(p[0]))
        angle = float(np.arccos(np.clip(n_cur @ n0, -1.0, 1.0)))
        n_valid = len(rv)
        if Jt is None or n_valid < cfg.min_pixels:
            return _rejected(f"too few road pixels ({n_valid} < {cfg.min_pixels})", n_cur, h,
                             n_pixels=n_valid, normal_angle_rad=angle)
        sigma_r = _robust_sigma(rv, cfg.mad_samples)
        w = _huber_weights(rv, sigma_r, cfg.huber_k)
        try:
            cov = sigma_r ** 2 * np.linalg.inv((Jt * w) @ Jt.T)
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
