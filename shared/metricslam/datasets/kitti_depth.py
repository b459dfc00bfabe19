"""KITTI-raw-style colour images with projected LiDAR depth (the depth-benchmark encoding).

Layout of a folder ``D`` (as ``../shared/data/kitti_raw_lidar``)::

    D/image_02/0000000000.png …      left colour camera (rectified), RGB
    D/depth_02/0000000000.png …      uint16 depth of the same view, metres × 256, 0 = none
    D/calib.txt                      "K: fx fy cx cy" or "P_rect_02: 12 numbers" (3x4)
    D/image_02/timestamps.txt        optional, KITTI raw "YYYY-MM-DD hh:mm:ss.fffffffff"

A depth PNG may be missing for some images (``Frame.depth_m`` is None then). No stereo, no
ground-truth poses. Without timestamps frames are 10 Hz apart.
"""

from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from metricslam.calibration import Calibration, reader_camera
from metricslam.datasets._common import (
    NOMINAL_PERIOD_NS,
    FileSequence,
    image_size,
    list_images,
    read_float_fields,
)
from metricslam.errors import CalibrationError, DatasetError


def read_raw_calib(path: Path, camera_key: str = "02") -> np.ndarray:
    """3x3 K from ``K: fx fy cx cy`` or ``P_rect_<cam>: 12 numbers``.

    Raises:
        CalibrationError: missing file, malformed line, or neither key present.
    """
    if not path.is_file():
        raise CalibrationError("calibration file does not exist (expected 'K: fx fy cx cy')", path)
    K = P = None
    for line_no, raw in enumerate(path.read_text().splitlines(), start=1):
        text = raw.strip()
        if not text or text.startswith("#") or ":" not in text:
            continue
        key, values = (s.strip() for s in text.split(":", 1))
        if key == "K":
            v = read_float_fields(values, None, path, line_no, "K", CalibrationError)
            if v.size == 4:
                K = np.array([[v[0], 0, v[2]], [0, v[1], v[3]], [0, 0, 1]], dtype=float)
            elif v.size == 9:
                K = v.reshape(3, 3)
            else:
                raise CalibrationError(
                    f"expected 'K: fx fy cx cy' (4 numbers) or a 3x3 K (9), got {v.size}",
                    path, line_no,
                )
        elif key == f"P_rect_{camera_key}":
            P = read_float_fields(values, 12, path, line_no, key, CalibrationError).reshape(3, 4)
    if K is None and P is None:
        raise CalibrationError(f"no 'K:' or 'P_rect_{camera_key}:' line", path)
    return K if K is not None else P[:, :3]


def read_raw_timestamps(path: Path, n_images: int) -> np.ndarray:
    """KITTI raw ``timestamps.txt`` -> (N,) int64 ns since the Unix epoch (UTC)."""
    lines = [(i, s.strip()) for i, s in enumerate(path.read_text().splitlines(), 1) if s.strip()]
    if len(lines) != n_images:
        raise DatasetError(f"has {len(lines)} timestamps for {n_images} images", path)
    out = []
    for line_no, text in lines:
        try:
            date, frac = (text.split(".") + ["0"])[:2]
            base = datetime.strptime(date, "%Y-%m-%d %H:%M:%S").replace(tzinfo=timezone.utc)
            ns = int(frac.ljust(9, "0")[:9])
        except ValueError:
            raise DatasetError(
                f"expected 'YYYY-MM-DD hh:mm:ss.fffffffff', got {text!r}", path, line_no
            ) from None
        out.append(int(base.timestamp()) * 1_000_000_000 + ns)
    return np.asarray(out, dtype=np.int64)


class KittiRawDepth(FileSequence):
    """Colour frames with LiDAR depth as a :class:`~metricslam.datasets.base.Sequence`.

    Args:
        folder: the dataset folder (contains ``image_02/``, ``depth_02/``, ``calib.txt``).
        camera_key: ``"02"`` (left colour) or ``"03"``; selects ``image_XX``/``depth_XX``.
        calibration: intrinsics to use instead of ``calib.txt``'s (:mod:`metricslam.calibration`).
    """

    def __init__(self, folder: str | Path, camera_key: str = "02",
                 calibration: Calibration | None = None) -> None:
        folder = Path(folder)
        if not folder.is_dir():
            raise DatasetError("KITTI raw depth folder does not exist", folder)
        images = list_images(folder / f"image_{camera_key}", (".png",))
        calib_path = folder / "calib.txt"
        K = read_raw_calib(calib_path, camera_key)
        w, h = image_size(images[0])
        camera, maps = reader_camera(calibration, K, w, h, calib_path)
        depth_dir = folder / f"depth_{camera_key}"
        if not depth_dir.is_dir():
            raise DatasetError("depth folder does not exist (uint16 PNGs, metres × 256)", depth_dir)
        depth_paths = [(depth_dir / p.name) if (depth_dir / p.name).is_file() else None
                       for p in images]
        ts = folder / f"image_{camera_key}" / "timestamps.txt"
        stamps = (read_raw_timestamps(ts, len(images)) if ts.is_file()
                  else np.arange(len(images), dtype=np.int64) * NOMINAL_PERIOD_NS)
        super().__init__(
            name=folder.name, camera=camera, baseline_m=None, image_paths=images,
            stamps_ns=stamps, depth_paths=depth_paths, depth_scale_per_m=256.0, color=True,
            undistort_maps=maps,
        )
        self.folder = folder
