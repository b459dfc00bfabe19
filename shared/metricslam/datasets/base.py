"""The one interface every dataset reader implements.

A :class:`Sequence` is an indexable list of :class:`Frame` with a camera, optional stereo
baseline and optional ground truth ``T_world_cam`` (left camera). Images load lazily.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from metricslam.camera import PinholeCamera


@dataclass(frozen=True)
class Frame:
    """One camera frame.

    Attributes:
        index: 0-based frame index in its sequence.
        t_ns: timestamp in nanoseconds.
        image: left image, (H, W) uint8 gray or (H, W, 3) uint8 RGB.
        camera: intrinsics of ``image``.
        image_right: rectified right image of a stereo pair, same shape, or None.
        baseline_m: stereo baseline in metres (right camera at +x), or None.
        T_world_cam: ground-truth pose of the left camera (4, 4), or None. Never fed to an
            estimator: only evaluators read it.
        depth_m: ground-truth depth of the left image (H, W) float32 metres (0 = unknown), or
            None (synthetic sequences and LiDAR sets have it). Never fed to an estimator.
    """

    index: int
    t_ns: int
    image: np.ndarray
    camera: PinholeCamera
    image_right: np.ndarray | None = None
    baseline_m: float | None = None
    T_world_cam: np.ndarray | None = None
    depth_m: np.ndarray | None = None


@runtime_checkable
class Sequence(Protocol):
    """A dataset sequence. Readers raise :class:`metricslam.errors.DatasetError` on bad files."""

    name: str
    camera: PinholeCamera
    baseline_m: float | None

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> Frame: ...

    @property
    def t_ns(self) -> np.ndarray:
        """Timestamps (N,) int64 nanoseconds."""
        ...

    @property
    def T_world_cam_gt(self) -> np.ndarray | None:
        """Ground-truth poses (N, 4, 4) of the left camera, or None."""
        ...
