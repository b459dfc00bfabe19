"""Photos of a printed chessboard seen by a synthetic rig's camera, for ``metricslam calibrate``.

A rendered sequence already carries its exact intrinsics (``calib.txt``); these photos let the
calibration step of a real rig (``docs/own_camera.md``) be run, and checked, on a rendered one:
the fitted ``fx, fy, cx, cy`` must come back as the rig's. The board is OpenCV's ``pattern.png``
layout, 10x7 squares (9x6 inner corners, :func:`metricslam.chessboard.board_points` order), at
varied tilts, distances and image positions; the camera has no lens distortion.

Example::

    photos = board_photos(camera, n=15, seed=0)       # list of (H, W) uint8 gray images
    result = calibrate_chessboard([(f"{i}", p) for i, p in enumerate(photos)], (9, 6), 0.025)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.errors import SynthError
from metricslam.geometry import so3

#: inner corners (columns, rows) and square side of the rendered board
INNER_CORNERS = (9, 6)
SQUARE_M = 0.025
_SQUARE_PX = 40  # texture resolution of one square
_MARGIN_PX = 40  # white border around the squares, in texture pixels


def _board_texture() -> np.ndarray:
    """The board as a uint8 image: white border, (cols+1) x (rows+1) squares, black first."""
    cols, rows = INNER_CORNERS[0] + 1, INNER_CORNERS[1] + 1
    tex = np.full((rows * _SQUARE_PX + 2 * _MARGIN_PX, cols * _SQUARE_PX + 2 * _MARGIN_PX), 255, np.uint8)
    for r in range(rows):
        for c in range(cols):
            if (r + c) % 2 == 0:
                y0, x0 = _MARGIN_PX + r * _SQUARE_PX, _MARGIN_PX + c * _SQUARE_PX
                tex[y0:y0 + _SQUARE_PX, x0:x0 + _SQUARE_PX] = 0
    return tex


def render_board(camera: PinholeCamera, R_cam_board: np.ndarray, t_cam_board: np.ndarray) -> np.ndarray:
    """The board at pose (``R_cam_board`` (3, 3), ``t_cam_board`` (3,) m; board frame: origin at
    inner corner (0, 0), x along a row, z out of the board) as an (H, W) uint8 photo, gray
    background."""
    import cv2

    q = SQUARE_M / _SQUARE_PX  # metres per texture pixel
    o = _MARGIN_PX + _SQUARE_PX - 0.5  # texture coordinate of inner corner (0, 0)
    A = np.array([[q, 0, -o * q], [0, q, -o * q], [0, 0, 1]])
    H = camera.K @ np.column_stack([R_cam_board[:, 0], R_cam_board[:, 1], t_cam_board]) @ A
    return cv2.warpPerspective(_board_texture(), H, (camera.width_px, camera.height_px),
                               flags=cv2.INTER_AREA, borderValue=128)


def board_photos(camera: PinholeCamera, n: int, seed: int) -> list[np.ndarray]:
    """``n`` photos (H, W) uint8 of the board: tilted up to ~30° about each axis, filling 30–50 %
    of the image width, spread over the image (what docs/calibration.md asks of real photos; a
    strongly tilted board near an edge may leave the view, and calibrate then rejects it)."""
    if n < 1:
        raise SynthError(f"number of board photos must be >= 1, got {n}")
    rng = np.random.default_rng([seed, 4242])
    cols, rows = INNER_CORNERS
    centre_board = np.array([(cols - 1) * SQUARE_M / 2, (rows - 1) * SQUARE_M / 2, 0.0])
    width_m = (cols + 1) * SQUARE_M
    photos = []
    for _ in range(n):
        R = so3.exp([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)])
        fill = rng.uniform(0.3, 0.5)
        z = camera.fx_px * width_m / (fill * camera.width_px)
        # where the board's centre goes, kept inside the image with room for its size
        room = 0.5 * (1.0 - fill) * 0.7
        u = camera.width_px * (0.5 + rng.uniform(-room, room))
        v = camera.height_px * (0.5 + rng.uniform(-room, room))
        centre_cam = np.array([(u - camera.cx_px) / camera.fx_px, (v - camera.cy_px) / camera.fy_px, 1.0]) * z
        photos.append(render_board(camera, R, centre_cam - R @ centre_board))
    return photos


def write_board_photos(out_dir: str | Path, camera: PinholeCamera, n: int, seed: int) -> Path:
    """Write :func:`board_photos` as ``OUT_DIR/board_photos/NNNNNN.png``; returns that folder."""
    import cv2

    folder = Path(out_dir) / "board_photos"
    folder.mkdir(parents=True, exist_ok=True)
    for i, photo in enumerate(board_photos(camera, n, seed)):
        if not cv2.imwrite(str(folder / f"{i:06d}.png"), photo):
            raise SynthError(f"could not write {folder / f'{i:06d}.png'}; check disk space")
    return folder
