"""Test support for the training tests: a blurred random texture and the synthetic pair's size."""

from __future__ import annotations

import cv2
import numpy as np

H, W = 64, 128  # network input of the training tests
SHIFT_PX = 6  # true disparity of the synthetic fronto-parallel pair


def texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """(h, w) float32 in [0, 1]: smooth random texture (block matching and the photometric loss
    need structure)."""
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(0, 1, (h, w)).astype(np.float32), (5, 5), 1.0)
