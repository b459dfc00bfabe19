"""Pinhole camera model (no distortion: inputs are rectified).

Pixel convention: ``(u, v)`` with the origin at the centre of the top-left pixel, so resizing
an image by ``sx`` maps ``u → (u + 0.5)·sx − 0.5``. See ``docs/conventions.md``.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from metricslam.errors import CameraError

#: plausible intrinsics (:func:`check_intrinsics`): focal lengths in (0, MAX_FOCAL_PX] px, image
#: sides in [1, MAX_IMAGE_SIDE_PX] px, principal point within [-width, 2·width] x [-height, 2·height].
MAX_FOCAL_PX = 1e5
MAX_IMAGE_SIDE_PX = 16384


def check_intrinsics(fx_px: float, fy_px: float, cx_px: float, cy_px: float,
                     width_px: int, height_px: int) -> None:
    """Refuse intrinsics no real camera has: non-finite values, focal lengths outside
    (0, :data:`MAX_FOCAL_PX`] px, image sides outside [1, :data:`MAX_IMAGE_SIDE_PX`] px, a
    principal point outside [-width, 2·width] x [-height, 2·height] px.

    The one check every way in uses (:class:`PinholeCamera` runs it, so the wire codec, the SLAM
    service and the ``camera`` command do too): a 1e308 px focal length used to be accepted and
    cost over a second per frame.

    Raises:
        CameraError: saying which value is out of range and what range is plausible.
    """
    values = {"fx_px": fx_px, "fy_px": fy_px, "cx_px": cx_px, "cy_px": cy_px,
              "width_px": width_px, "height_px": height_px}
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise CameraError(f"{name} must be a finite number, got {value!r}")
    for name in ("width_px", "height_px"):
        if not 1 <= values[name] <= MAX_IMAGE_SIDE_PX:
            raise CameraError(f"{name} must be in [1, {MAX_IMAGE_SIDE_PX}] px, got {values[name]}")
    for name in ("fx_px", "fy_px"):
        if not 0 < values[name] <= MAX_FOCAL_PX:
            raise CameraError(f"{name} must be in (0, {MAX_FOCAL_PX:g}] px, got {values[name]!r}; "
                              "pass the focal length in pixels at the image's resolution")
    for name, side in (("cx_px", width_px), ("cy_px", height_px)):
        if not -side <= values[name] <= 2 * side:
            raise CameraError(f"{name} = {values[name]!r} px is outside [-{side}, {2 * side}] px for a "
                              f"{width_px}x{height_px} image; the principal point is near its centre")


class PinholeCamera(BaseModel):
    """Intrinsics of a rectified pinhole camera, in pixels, for an image of ``width × height``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    fx_px: float = Field(gt=0)
    fy_px: float = Field(gt=0)
    cx_px: float
    cy_px: float
    width_px: int = Field(gt=0)
    height_px: int = Field(gt=0)

    @model_validator(mode="after")
    def _plausible(self) -> "PinholeCamera":
        try:
            check_intrinsics(self.fx_px, self.fy_px, self.cx_px, self.cy_px, self.width_px, self.height_px)
        except CameraError as exc:  # pydantic reports ValueErrors as validation errors
            raise ValueError(str(exc)) from None
        return self

    @classmethod
    def from_K(cls, K: np.ndarray, width_px: int, height_px: int) -> "PinholeCamera":
        """From a 3x3 (or the left 3x3 of a 3x4 projection) matrix."""
        K = np.asarray(K, dtype=float)
        if K.shape not in ((3, 3), (3, 4)) or not np.all(np.isfinite(K)):
            raise CameraError(f"expected a finite 3x3 K or 3x4 P matrix, got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CameraError(f"focal lengths must be > 0, got fx={K[0, 0]}, fy={K[1, 1]}")
        check_intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                         int(width_px), int(height_px))
        return cls(fx_px=K[0, 0], fy_px=K[1, 1], cx_px=K[0, 2], cy_px=K[1, 2],
                   width_px=int(width_px), height_px=int(height_px))

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    def resized(self, width_px: int, height_px: int) -> "PinholeCamera":
        """Intrinsics for the same camera after resizing the image to ``width × height``."""
        sx = width_px / self.width_px
        sy = height_px / self.height_px
        return PinholeCamera(
            fx_px=self.fx_px * sx, fy_px=self.fy_px * sy,
            cx_px=(self.cx_px + 0.5) * sx - 0.5, cy_px=(self.cy_px + 0.5) * sy - 0.5,
            width_px=int(width_px), height_px=int(height_px),
        )

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Points in the camera frame (N, 3), z > 0 -> pixels (N, 2). Points with z <= 0 give NaN."""
        p = np.atleast_2d(np.asarray(p_cam, dtype=float))
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx_px * p[:, 0] / z + self.cx_px
            v = self.fy_px * p[:, 1] / z + self.cy_px
        uv = np.stack([u, v], axis=1)
        uv[z <= 0] = np.nan
        return uv

    def unproject(self, uv_px: np.ndarray, depth_m: np.ndarray | float = 1.0) -> np.ndarray:
        """Pixels (N, 2) and depth along z (N,) or scalar -> points in the camera frame (N, 3)."""
        uv = np.atleast_2d(np.asarray(uv_px, dtype=float))
        d = np.broadcast_to(np.asarray(depth_m, dtype=float), (uv.shape[0],))
        x = (uv[:, 0] - self.cx_px) / self.fx_px
        y = (uv[:, 1] - self.cy_px) / self.fy_px
        return np.stack([x * d, y * d, d], axis=1)

    def normalized(self, uv_px: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> normalized image coordinates (N, 2) (z = 1 plane)."""
        return self.unproject(uv_px, 1.0)[:, :2]

    def in_image(self, uv_px: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Boolean mask (N,) of pixels inside the image with a margin."""
        uv = np.atleast_2d(np.asarray(uv_px, dtype=float))
        return (
            np.isfinite(uv).all(axis=1)
            & (uv[:, 0] >= -0.5 + margin_px) & (uv[:, 0] <= self.width_px - 0.5 - margin_px)
            & (uv[:, 1] >= -0.5 + margin_px) & (uv[:, 1] <= self.height_px - 0.5 - margin_px)
        )
