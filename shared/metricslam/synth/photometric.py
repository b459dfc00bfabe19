"""Camera effects on rendered radiance: exposure changes, vignetting, noise, motion blur.

Radiance from :mod:`metricslam.synth.render` is about 0..1; :func:`to_uint8` turns it into an
8-bit gray image the way a camera would: ``gain · vignetting · radiance · 255 + noise``.
Everything is driven by explicit seeds, so sequences are byte-identical for a seed.
"""

from __future__ import annotations

import functools

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from metricslam.geometry import se3


class PhotometricConfig(BaseModel):
    """Photometric realism. ``motion_blur_samples`` ≤ 1 disables motion blur."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    exposure_log_sigma: float = Field(0.12, ge=0, description="std of log exposure gain")
    exposure_corr_frames: float = Field(40.0, gt=0, description="correlation time of exposure")
    vignetting: float = Field(0.3, ge=0, lt=1, description="relative darkening at the corners")
    noise_sigma: float = Field(1.5, ge=0, description="gaussian noise std, gray levels")
    right_gain: float = Field(1.0, gt=0, description="gain of the right camera relative to left")
    motion_blur_samples: int = Field(0, ge=0, le=16, description="sub-frame renders averaged")
    shutter_fraction: float = Field(0.5, gt=0, le=1, description="exposure / frame interval")


def exposure_gains(n_frames: int, seed: int, cfg: PhotometricConfig) -> np.ndarray:
    """Slowly varying exposure gains (n_frames,) around 1 (AR(1) in log space)."""
    rng = np.random.default_rng([seed, 9001])
    a = np.exp(-1.0 / cfg.exposure_corr_frames)
    log_g = np.zeros(n_frames)
    x = rng.normal(0.0, cfg.exposure_log_sigma)
    for i in range(n_frames):
        log_g[i] = x
        x = a * x + np.sqrt(1 - a * a) * rng.normal(0.0, cfg.exposure_log_sigma)
    return np.exp(log_g)


@functools.lru_cache(maxsize=8)
def vignetting_map(width_px: int, height_px: int, strength: float) -> np.ndarray:
    """(H, W) float32 gain, 1 at the centre, ``1 - strength`` at the corners (quadratic)."""
    u = (np.arange(width_px) - (width_px - 1) / 2) / ((width_px - 1) / 2)
    v = (np.arange(height_px) - (height_px - 1) / 2) / ((width_px - 1) / 2)
    r2 = (u[None, :] ** 2 + v[:, None] ** 2) / (1.0 + ((height_px - 1) / (width_px - 1)) ** 2)
    out = (1.0 - strength * r2).astype(np.float32)
    out.flags.writeable = False
    return out


def to_uint8(radiance: np.ndarray, gain: float, rng: np.random.Generator,
             cfg: PhotometricConfig) -> np.ndarray:
    """Radiance (H, W) float32 -> gray image (H, W) uint8 with gain, vignetting and noise."""
    h, w = radiance.shape
    img = radiance * np.float32(gain * 255.0) * vignetting_map(w, h, cfg.vignetting)
    if cfg.noise_sigma > 0:
        img += rng.standard_normal((h, w), dtype=np.float32) * np.float32(cfg.noise_sigma)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def blur_poses(T_world_cam: np.ndarray, index: int, cfg: PhotometricConfig) -> list[np.ndarray]:
    """Poses (4, 4) spread over the shutter time of frame ``index`` (centred on it)."""
    n = cfg.motion_blur_samples
    T_i = T_world_cam[index]
    if n <= 1 or len(T_world_cam) < 2:
        return [T_i]
    j = index + 1 if index + 1 < len(T_world_cam) else index - 1
    xi = se3.log(se3.inverse(T_i) @ T_world_cam[j]) * (1.0 if j > index else -1.0)
    taus = np.linspace(-0.5, 0.5, n) * cfg.shutter_fraction
    return [T_i @ se3.exp(tau * xi) for tau in taus]
