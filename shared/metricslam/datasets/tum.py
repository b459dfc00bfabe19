"""TUM RGB-D reader: ``rgb.txt`` images, optional ``depth.txt`` depth, ``groundtruth.txt`` poses.

Layout of a sequence folder ``SEQ`` (e.g. ``rgbd_dataset_freiburg1_xyz``)::

    SEQ/rgb.txt            "timestamp filename" per line, "#" comments, seconds
    SEQ/rgb/<t>.png        colour images
    SEQ/depth.txt          optional, same format; SEQ/depth/<t>.png uint16, metres × 5000
    SEQ/groundtruth.txt    "timestamp tx ty tz qx qy qz qw" (xyzw quaternion), T_world_cam

Association: each image takes the ground-truth pose (and depth image) with the nearest
timestamp within ``max_diff_ns`` (default 20 ms, as TUM's ``associate.py``). When ground truth
exists, images without a match are dropped so every frame has a pose.

Intrinsics: TUM folders carry none, and metric scale depends on them. In order: ``calibration=``
(``run --calib FILE.yaml``, :mod:`metricslam.calibration`; undistorted at load when it has
distortion), ``camera=`` (an undistorted pinhole camera), else the published Freiburg 1/2/3
calibration (:data:`TUM_CALIBRATIONS`) picked from the folder name (``freiburg1``/``fr1`` …),
logged as a warning because a folder name is only a hint; Freiburg 1 and 2 images are
undistorted with the published coefficients, Freiburg 3 images already are. Anything else is
refused with a :class:`~metricslam.errors.CalibrationError` saying to pass ``--calib``: there is
no default guess.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from metricslam.calibration import Calibration, camera_and_maps, make_calibration
from metricslam.camera import PinholeCamera
from metricslam.datasets._common import FileSequence, image_size
from metricslam.errors import CalibrationError, DatasetError
from metricslam.trajectory.io import read_tum, seconds_text_to_ns

log = logging.getLogger(__name__)

#: published calibrations of the TUM RGB-D colour cameras at 640x480 (the dataset's "file
#: formats" page): (fx, fy, cx, cy), OpenCV radtan (k1, k2, p1, p2, k3). Freiburg 3 images were
#: undistorted by the dataset's authors.
TUM_CALIBRATIONS = {
    "fr1": ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": ((535.4, 539.2, 320.1, 247.6), ()),
}
#: TUM depth PNG value per metre.
TUM_DEPTH_SCALE_PER_M = 5000.0


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """``rgb.txt``/``depth.txt`` -> ``(t_ns (N,), relative file names)``."""
    if not path.is_file():
        raise DatasetError("file list does not exist (expected 'timestamp filename' lines)", path)
    stamps, names = [], []
    for line_no, raw in enumerate(path.read_text().splitlines(), start=1):
        text = raw.strip()
        if not text or text.startswith("#"):
            continue
        parts = text.split()
        if len(parts) != 2:
            raise DatasetError(f"expected 'timestamp filename', got {text[:60]!r}", path, line_no)
        try:
            stamps.append(seconds_text_to_ns(parts[0], path, line_no))
        except DatasetError as exc:
            raise DatasetError(f"expected a timestamp in seconds, got {parts[0]!r}", path, line_no) from exc
        names.append(parts[1])
    if not names:
        raise DatasetError("lists no files", path)
    t = np.asarray(stamps, dtype=np.int64)
    if np.any(np.diff(t) <= 0):
        raise DatasetError("timestamps must increase strictly", path)
    return t, names


def nearest(t_ref_ns: np.ndarray, t_query_ns: np.ndarray, max_diff_ns: int) -> np.ndarray:
    """Index into sorted ``t_ref_ns`` of the nearest stamp for each query, -1 if none within tolerance."""
    pos = np.clip(np.searchsorted(t_ref_ns, t_query_ns), 1, len(t_ref_ns) - 1) if len(t_ref_ns) > 1 \
        else np.zeros(len(t_query_ns), dtype=np.int64)
    left = np.maximum(pos - 1, 0)
    pick = np.where(np.abs(t_ref_ns[left] - t_query_ns) <= np.abs(t_ref_ns[pos] - t_query_ns), left, pos)
    ok = np.abs(t_ref_ns[pick] - t_query_ns) <= max_diff_ns
    return np.where(ok, pick, -1)


def published_calibration(name: str) -> Calibration | None:
    """The published calibration of the Freiburg camera a folder name names (``freiburg1`` /
    ``fr1`` …) at 640x480, or None when it names none."""
    m = re.search(r"(?:freiburg|fr)([123])", name.lower())
    if m is None:
        return None
    key = f"fr{m.group(1)}"
    (fx, fy, cx, cy), coeffs = TUM_CALIBRATIONS[key]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return make_calibration(K, 640, 480, "radtan" if coeffs else "none", coeffs,
                            source=f"published TUM {key} calibration")


def tum_calibration(seq_dir: Path) -> Calibration:
    """The published calibration for a TUM folder by its name, with a warning that says so.

    Raises:
        CalibrationError: the name names no Freiburg camera (what to do instead is in the message).
    """
    calib = published_calibration(seq_dir.name)
    if calib is None:
        raise CalibrationError(
            "this TUM-layout folder carries no intrinsics and its name names no Freiburg camera "
            "(freiburg1/2/3 or fr1/2/3); metric scale depends on the intrinsics, so nothing is "
            "guessed: pass --calib FILE.yaml (calibration=; docs/calibration.md explains how to "
            "calibrate a camera)", seq_dir)
    c = calib.camera
    log.warning("%s: NO CALIBRATION GIVEN: using the %s (fx=%g fy=%g cx=%g cy=%g, distortion %s) "
                "because the folder name says so; metric scale is only right if these images come "
                "from that camera. Pass --calib FILE.yaml to be sure.", seq_dir, calib.source,
                c.fx_px, c.fy_px, c.cx_px, c.cy_px, list(calib.distortion_coefficients) or "none")
    return calib


class TumRgbd(FileSequence):
    """A TUM RGB-D sequence as a :class:`~metricslam.datasets.base.Sequence`.

    Args:
        seq_dir: the sequence folder (holds ``rgb.txt``).
        camera: pinhole intrinsics of undistorted images.
        calibration: intrinsics and distortion (wins over ``camera``); with neither, the
            published calibration named by the folder, else :class:`CalibrationError` (module doc).
        max_diff_ns: association tolerance for ground truth and depth.
        load_depth: associate ``depth.txt`` images into ``Frame.depth_m``.
        require_groundtruth: drop images without a ground-truth pose (when ground truth exists).
    """

    def __init__(
        self,
        seq_dir: str | Path,
        camera: PinholeCamera | None = None,
        max_diff_ns: int = 20_000_000,
        load_depth: bool = True,
        require_groundtruth: bool = True,
        calibration: Calibration | None = None,
    ) -> None:
        seq_dir = Path(seq_dir)
        if not seq_dir.is_dir():
            raise DatasetError("TUM sequence folder does not exist", seq_dir)
        stamps, names = read_file_list(seq_dir / "rgb.txt")
        files = [seq_dir / n for n in names]
        keep = np.ones(len(files), dtype=bool)
        poses = None
        gt_path = seq_dir / "groundtruth.txt"
        if gt_path.is_file():
            t_gt, T_gt = read_tum(gt_path)
            idx = nearest(t_gt, stamps, max_diff_ns)
            if np.all(idx < 0):
                raise DatasetError(
                    f"no image is within {max_diff_ns / 1e6:g} ms of a ground-truth pose", gt_path
                )
            if require_groundtruth:
                keep = idx >= 0
                if not keep.all():
                    log.info("%s: dropping %d images without ground truth", seq_dir, (~keep).sum())
                poses = T_gt[idx[keep]]
            elif np.all(idx >= 0):
                poses = T_gt[idx]
        stamps = stamps[keep]
        files = [f for f, k in zip(files, keep) if k]
        depth_paths = None
        if load_depth and (seq_dir / "depth.txt").is_file():
            t_d, d_names = read_file_list(seq_dir / "depth.txt")
            j = nearest(t_d, stamps, max_diff_ns)
            depth_paths = [seq_dir / d_names[k] if k >= 0 else None for k in j]
        maps = None
        if calibration is not None or camera is None:
            calibration = calibration if calibration is not None else tum_calibration(seq_dir)
            camera, maps = camera_and_maps(calibration, *image_size(files[0]))
        super().__init__(
            name=seq_dir.name, camera=camera, baseline_m=None, image_paths=files, stamps_ns=stamps,
            depth_paths=depth_paths, depth_scale_per_m=TUM_DEPTH_SCALE_PER_M, poses_gt=poses,
            color=True, undistort_maps=maps,
        )
