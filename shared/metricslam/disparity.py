"""Metric disparity <-> depth conversions.

``depth_m = fx_px·baseline_m / disparity_px``. The depth network's output is disparity as a
fraction of image width (``d_frac``), see ``docs/conventions.md``. Non-positive or non-finite
disparities map to ``inf`` depth / 0 inverse depth, never to an exception.
"""

from __future__ import annotations

import numpy as np

from metricslam.errors import CameraError


def _check(fx_px: float, baseline_m: float) -> None:
    if not (np.isfinite(fx_px) and fx_px > 0):
        raise CameraError(f"fx_px must be finite and > 0, got {fx_px}")
    if not (np.isfinite(baseline_m) and baseline_m > 0):
        raise CameraError(f"baseline_m must be finite and > 0, got {baseline_m}")


def depth_from_disparity(disparity_px: np.ndarray, fx_px: float, baseline_m: float) -> np.ndarray:
    """Depth in metres; ``inf`` where the disparity is <= 0 or non-finite."""
    _check(fx_px, baseline_m)
    d = np.asarray(disparity_px, dtype=np.float64)
    out = np.full(d.shape, np.inf)
    ok = np.isfinite(d) & (d > 0)
    out[ok] = fx_px * baseline_m / d[ok]
    return out


def disparity_from_depth(depth_m: np.ndarray, fx_px: float, baseline_m: float) -> np.ndarray:
    """Disparity in pixels; 0 where the depth is <= 0, inf or NaN."""
    _check(fx_px, baseline_m)
    z = np.asarray(depth_m, dtype=np.float64)
    out = np.zeros(z.shape)
    ok = np.isfinite(z) & (z > 0)
    out[ok] = fx_px * baseline_m / z[ok]
    return out


def inv_depth_from_disparity(disparity_px: np.ndarray, fx_px: float, baseline_m: float) -> np.ndarray:
    """Inverse depth in 1/m (paper: ``Z = D / (B·fx)``); 0 for non-positive disparity."""
    _check(fx_px, baseline_m)
    d = np.asarray(disparity_px, dtype=np.float64)
    return np.where(np.isfinite(d) & (d > 0), d, 0.0) / (fx_px * baseline_m)


def inv_depth_from_width_fraction(
    d_frac: np.ndarray, fx_px: float, width_px: float, baseline_m: float
) -> np.ndarray:
    """Network output (disparity / image width) -> metric inverse depth (1/m) for a camera with
    focal length ``fx_px`` at image width ``width_px`` and the model's training ``baseline_m``."""
    if not (np.isfinite(width_px) and width_px > 0):
        raise CameraError(f"width_px must be finite and > 0, got {width_px}")
    return inv_depth_from_disparity(np.asarray(d_frac, dtype=np.float64) * width_px, fx_px, baseline_m)
