"""Input checks and process set-up for the local VO: which frames are usable, BLAS threads."""

from __future__ import annotations

import logging

import cv2
import numpy as np

from metricslam.camera import PinholeCamera

log = logging.getLogger(__name__)


def usable_gray(image: object, camera: PinholeCamera, min_texture_std: float) -> np.ndarray | None:
    """The frame image as (H, W) uint8 gray, or None when it is unusable.

    Unusable: not an array, empty, not uint8 gray/RGB, not the camera's size, or blank (intensity
    std over a 4x-subsampled grid below ``min_texture_std``: lens cap, black or saturated frame).
    """
    img = image
    if not isinstance(img, np.ndarray) or img.size == 0:
        return None
    if img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.ndim != 2 or img.dtype != np.uint8:
        return None
    if img.shape != (camera.height_px, camera.width_px):
        return None
    if float(img[::4, ::4].std()) < min_texture_std:
        return None
    return img


def limit_blas_threads(n: int) -> None:
    """Cap OpenBLAS threads process-wide (the window's matrices are tiny; oversubscribed BLAS
    threads on a busy machine made one Schur product ~10x slower)."""
    try:
        import threadpoolctl
    except ImportError:  # optional: only a speed-up
        log.debug("threadpoolctl not installed; BLAS thread count left alone")
        return
    threadpoolctl.threadpool_limits(n, user_api="blas")
