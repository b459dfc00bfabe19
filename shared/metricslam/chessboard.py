"""Calibrating a camera from chessboard photos with OpenCV (``metricslam calibrate``).

``cv2.findChessboardCorners`` finds the inner corners of a printed chessboard in each photo
(refined to sub-pixel with ``cv2.cornerSubPix``); ``cv2.calibrateCamera`` (``cv2.fisheye.calibrate``
for a fisheye lens) fits intrinsics and distortion to all of them. The result is a
:class:`~metricslam.calibration.Calibration` whose :meth:`~metricslam.calibration.Calibration.to_yaml`
is the file ``--calib`` reads. How to take the photos: ``docs/calibration.md``.

Example::

    images = [(p.name, cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)) for p in sorted(folder.glob("*.png"))]
    result = calibrate_chessboard(images, inner_corners=(9, 6), square_m=0.025)
    Path("cam.yaml").write_text(result.calibration.to_yaml())
    print(result.rms_px)   # RMS reprojection error; well under 1 px for a good calibration
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from metricslam.calibration import Calibration, make_calibration
from metricslam.errors import CalibrationError

#: fewest photos with a detected board; OpenCV needs 3, a usable calibration 10-20 varied views
MIN_VIEWS = 3


@dataclass(frozen=True)
class ChessboardCalibration:
    """What :func:`calibrate_chessboard` found.

    Attributes:
        calibration: intrinsics and distortion for images of the photos' size.
        rms_px: RMS reprojection error over all corners (px).
        used: names of the photos the board was found in.
        rejected: names of the photos it was not found in.
    """

    calibration: Calibration
    rms_px: float
    used: list[str] = field(default_factory=list)
    rejected: list[str] = field(default_factory=list)


def board_points(inner_corners: tuple[int, int], square_m: float) -> np.ndarray:
    """The board's inner corners in its own frame (N, 3) float32 metres, z = 0, in OpenCV's order."""
    cols, rows = inner_corners
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2)
    return np.hstack([grid * square_m, np.zeros((grid.shape[0], 1))]).astype(np.float32)


def find_corners(gray: np.ndarray, inner_corners: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners (N, 1, 2) float32 px of a chessboard in a gray image, or None."""
    import cv2

    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, inner_corners, flags=flags)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    return cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria)


def calibrate_chessboard(images: Iterable[tuple[str, np.ndarray]], inner_corners: tuple[int, int] = (9, 6),
                         square_m: float = 0.025, fisheye: bool = False) -> ChessboardCalibration:
    """Fit intrinsics and distortion to chessboard photos.

    Args:
        images: ``(name, image)`` pairs, (H, W) uint8 gray or (H, W, 3) BGR, all of one size.
        inner_corners: inner corners per row and per column of the board (a board of 10x7
            squares has 9x6), the ``patternSize`` of ``cv2.findChessboardCorners``.
        square_m: side of one square (m); it scales only the board poses, not the intrinsics.
        fisheye: fit OpenCV's fisheye (equidistant) model instead of radial-tangential.

    Raises:
        CalibrationError: photos of different sizes, or the board found in fewer than
            :data:`MIN_VIEWS` of them.
    """
    import cv2

    obj = board_points(inner_corners, square_m)
    object_points, image_points, used, rejected = [], [], [], []
    size = None
    for name, img in images:
        gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
        if size is None:
            size = (gray.shape[1], gray.shape[0])
        elif (gray.shape[1], gray.shape[0]) != size:
            raise CalibrationError(f"{name} is {gray.shape[1]}x{gray.shape[0]} but the first photo is "
                                   f"{size[0]}x{size[1]}; calibrate one resolution at a time")
        corners = find_corners(gray, inner_corners)
        if corners is None:
            rejected.append(name)
            continue
        object_points.append(obj)
        image_points.append(corners)
        used.append(name)
    if len(used) < MIN_VIEWS:
        raise CalibrationError(
            f"found a {inner_corners[0]}x{inner_corners[1]}-inner-corner chessboard in {len(used)} of "
            f"{len(used) + len(rejected)} photos; need at least {MIN_VIEWS} (10-20 varied views for a "
            "good calibration). Check --pattern (inner corners, not squares) and that the whole "
            "board is in the picture, sharp and well lit")
    if fisheye:
        K = np.eye(3)
        D = np.zeros((4, 1))
        flags = cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
        rms, K, D, _, _ = cv2.fisheye.calibrate([o.reshape(-1, 1, 3).astype(np.float64) for o in object_points],
                                                [c.reshape(-1, 1, 2).astype(np.float64) for c in image_points],
                                                size, K, D, flags=flags)
        model = "equidistant"
    else:
        rms, K, D, _, _ = cv2.calibrateCamera(object_points, image_points, size, None, None)
        model = "radtan"
    calib = make_calibration(K, size[0], size[1], model, np.asarray(D).reshape(-1),
                             source=f"metricslam calibrate, {len(used)} views, RMS {rms:.3f} px")
    return ChessboardCalibration(calib, float(rms), used, rejected)
