"""Bilinear sampling of a coarse map at full-resolution pixel coordinates.

Pixel convention (``docs/conventions.md``): ``(u, v)`` = (column, row) with the origin at the
centre of the top-left pixel. A map of size (h, w) covering an image of size (W, H) has its
cell ``(j, i)`` centred at image pixel ``((j + 0.5)·W/w − 0.5, (i + 0.5)·H/h − 0.5)``. Points
outside the outermost cell centres are clamped to the border (edge replication).
"""

from __future__ import annotations

import numpy as np

from metricslam.errors import ImageError


def sample_map(map_hw: np.ndarray, uv_px: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Bilinearly sample ``map_hw`` (h, w) at image pixels ``uv_px`` (N, 2).

    Args:
        map_hw: (h, w) map covering the whole image (e.g. the network's inverse depth, 1/m).
        uv_px: (N, 2) pixel coordinates (u, v) in the full image of size ``image_size``.
        image_size: (W, H) of the image the coordinates refer to, pixels.

    Returns:
        (N,) float64 samples. NaN coordinates give NaN.
    """
    grid = np.asarray(map_hw, dtype=np.float64)
    if grid.ndim != 2 or grid.shape[0] < 1 or grid.shape[1] < 1:
        raise ImageError(f"map_hw must be a non-empty (h, w) array, got shape {grid.shape}")
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    width_px, height_px = image_size
    if width_px <= 0 or height_px <= 0:
        raise ImageError(f"image_size must be positive (W, H), got {image_size}")
    h, w = grid.shape
    # image pixel -> map cell coordinates (same centre convention)
    x = (uv[:, 0] + 0.5) * (w / width_px) - 0.5
    y = (uv[:, 1] + 0.5) * (h / height_px) - 0.5
    nan = ~(np.isfinite(x) & np.isfinite(y))
    x = np.clip(np.nan_to_num(x), 0.0, w - 1.0)
    y = np.clip(np.nan_to_num(y), 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    ax = x - x0
    ay = y - y0
    top = grid[y0, x0] * (1 - ax) + grid[y0, x1] * ax
    bottom = grid[y1, x0] * (1 - ax) + grid[y1, x1] * ax
    out = top * (1 - ay) + bottom * ay
    out[nan] = np.nan
    return out
