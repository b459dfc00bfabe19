"""Wire messages that describe the map rather than one frame: the local window's landmarks and
a keyframe's coarse metric depth. Encoded by :mod:`metricslam.wire.codec` like every message
(its ``MESSAGE_TYPES`` lists them).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from pydantic import Field, field_validator

from metricslam.wire.base import FrameId, Message, as_array


class LandmarksMessage(Message):
    """The local window's landmarks after a keyframe (``metricslam/<id>/landmarks``).

    ``points_world``: (N, 3) float32 landmark positions in the SLAM world frame (world units:
    metres once ``scale_established``), those with a known depth; ``frame_index``/``t_ns``: the
    keyframe that triggered it; ``frame_id``: their frame (``"map"``: the saved map's, metres).
    """

    KIND: ClassVar[str] = "landmarks"
    ARRAYS: ClassVar[tuple[str, ...]] = ("points_world",)

    frame_index: int = Field(ge=0)
    t_ns: int = Field(ge=0)
    scale_established: bool = False
    frame_id: FrameId = "world"
    points_world: np.ndarray

    @field_validator("points_world")
    @classmethod
    def _points(cls, points: Any) -> np.ndarray:
        return as_array(points, "float32", "points_world", (None, 3))


class KeyframeDepthMessage(Message):
    """A keyframe's coarse metric inverse depth, as the depth source answered it
    (``metricslam/<id>/keyframe_depth``; the back end's ``ScaleMeasured`` event).

    ``inv_depth_per_m``: (h, w) float32 metric inverse depth (1/m) on the network's coarse grid
    (e.g. 32x64), covering the whole ``image_width_px`` x ``image_height_px`` keyframe image.
    """

    KIND: ClassVar[str] = "keyframe_depth"
    ARRAYS: ClassVar[tuple[str, ...]] = ("inv_depth_per_m",)

    frame_index: int = Field(ge=0)
    t_ns: int = Field(ge=0)
    image_width_px: int = Field(gt=0)
    image_height_px: int = Field(gt=0)
    inv_depth_per_m: np.ndarray

    @field_validator("inv_depth_per_m")
    @classmethod
    def _grid(cls, grid: Any) -> np.ndarray:
        return as_array(grid, "float32", "inv_depth_per_m", (None, None))

    def depth_m(self) -> np.ndarray:
        """(h, w) float32 depth in metres; NaN where the inverse depth is not positive."""
        inv = self.inv_depth_per_m
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(inv > 0, 1.0 / inv, np.nan).astype(np.float32)
