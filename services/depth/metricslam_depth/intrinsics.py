"""The caller's camera as a request gives it: ``fx`` (required), ``fy``, ``cx``, ``cy`` (optional).

Pixels of the **uploaded** image, origin at the centre of its top-left pixel (``docs/conventions.md``,
as :class:`~metricslam.camera.PinholeCamera`). Defaults, applied per image: ``fy = fx``,
``cx = (width − 1)/2``, ``cy = (height − 1)/2`` (the image centre; the same as ``metricslam
camera``'s). The principal point must lie on the image, ``0 <= cx <= width`` and ``0 <= cy <=
height``; that needs the decoded (EXIF-upright) size, so it is checked after decoding (422).

Version-1 models use only ``fx``; version-2 (canonical-camera) models use all four.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from metricslam.camera import PinholeCamera, check_intrinsics
from metricslam.errors import CameraError

from .errors import RequestProblem


def _invalid(detail: str) -> RequestProblem:
    return RequestProblem(422, "invalid-parameter", "Invalid request parameter", detail)


@dataclass(frozen=True)
class CameraQuery:
    """Intrinsics from the query string (already range-checked by the route, except cx/cy's
    upper bounds, which depend on the image).

    Attributes:
        fx_px: focal length along x, px at the uploaded resolution.
        fy_px / cx_px / cy_px: None when the request did not give them (module defaults).
    """

    fx_px: float
    fy_px: float | None = None
    cx_px: float | None = None
    cy_px: float | None = None

    @property
    def fy_or_fx(self) -> float:
        """``fy``, or ``fx`` when the request gave none (square pixels)."""
        return self.fx_px if self.fy_px is None else self.fy_px

    def principal_point(self, width_px: int, height_px: int) -> tuple[float, float]:
        """``(cx, cy)`` for an uploaded image of ``width × height`` px (defaults: its centre).

        Raises:
            RequestProblem: 422 when the principal point is off the image.
        """
        cx = (width_px - 1) / 2.0 if self.cx_px is None else float(self.cx_px)
        cy = (height_px - 1) / 2.0 if self.cy_px is None else float(self.cy_px)
        for name, value, side, what in (("cx", cx, width_px, "width"), ("cy", cy, height_px, "height")):
            if not (math.isfinite(value) and 0.0 <= value <= side):
                raise _invalid(
                    f"{name}={value:g} is off the {width_px}x{height_px} image: the principal point is in "
                    f"pixels of the uploaded image, 0 <= {name} <= {what} ({side}); leave {name} out for "
                    "the image centre")
        return cx, cy

    def camera(self, width_px: int, height_px: int) -> PinholeCamera:
        """The :class:`PinholeCamera` of an uploaded image of ``width × height`` px.

        Raises:
            RequestProblem: 422 for intrinsics no camera has (off-image principal point, ...).
        """
        cx, cy = self.principal_point(width_px, height_px)
        values = {"fx_px": float(self.fx_px), "fy_px": float(self.fy_or_fx), "cx_px": cx, "cy_px": cy,
                  "width_px": int(width_px), "height_px": int(height_px)}
        try:
            check_intrinsics(**values)
        except CameraError as exc:  # says which value and the plausible range
            raise _invalid(f"fx/fy/cx/cy do not describe a {width_px}x{height_px} camera: {exc}") from None
        return PinholeCamera(**values)


def decoded_camera(camera: PinholeCamera, decoded_size_px: tuple[int, int]) -> PinholeCamera:
    """``camera`` (of the uploaded image) for the image as decoded, possibly reduced 2x or 4x in
    the JPEG DCT (:func:`~metricslam_depth.imaging.decode_gray`): decoded pixel ``k`` covers
    uploaded pixels ``f·k … f·k + f − 1``, so ``u_dec = (u + 0.5)/f − 0.5`` and ``fx_dec = fx/f``
    (exact, even where the last decoded pixel is a partial one)."""
    width_px, height_px = int(decoded_size_px[0]), int(decoded_size_px[1])
    if (width_px, height_px) == (camera.width_px, camera.height_px):
        return camera
    factor = round(camera.width_px / width_px)
    return PinholeCamera(fx_px=camera.fx_px / factor, fy_px=camera.fy_px / factor,
                         cx_px=(camera.cx_px + 0.5) / factor - 0.5, cy_px=(camera.cy_px + 0.5) / factor - 0.5,
                         width_px=width_px, height_px=height_px)
