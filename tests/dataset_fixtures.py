"""Tiny image/pose fixtures shared by the dataset-reader tests (imported by tests/test_datasets*.py)."""

from __future__ import annotations

import numpy as np
from metricslam.geometry import se3

W, H = 40, 30
FX, CX, CY, B = 50.0, 19.5, 14.5, 0.5


def gray(i: int) -> np.ndarray:
    img = np.full((H, W), 10 * i % 256, np.uint8)
    img[i % H, :] = 255
    return img


def poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([se3.exp(np.concatenate([rng.normal(0, 0.1, 3), [0, 0, float(i)]]))
                     for i in range(n)])
