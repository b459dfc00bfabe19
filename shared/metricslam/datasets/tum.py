"""TUM RGB-D reader: ``rgb.txt`` images, optional ``depth.txt`` depth, ``groundtruth.txt`` poses.

Layout of a sequence folder ``SEQ`` (e.g. ``rgbd_dataset_freiburg1_xyz``)::

    SEQ/rgb.txt            "timestamp filename" per line, "#" comments, seconds
    SEQ/rgb/<t>.png        colour images
    SEQ/depth.txt          optional, same format; SEQ/depth/<t>.png uint16, metres × 5000
    SEQ/groundtruth.txt    "timestamp tx ty tz qx qy qz qw" (xyzw quaternion), T_world_cam

Association: each image takes the ground-truth pose (and depth image) with the nearest
timestamp within ``max_diff_ns`` (default 20 ms, as TUM's ``associate.py``). When ground truth
exists, images without a match are dropped so every frame has a pose. TUM folders carry no
intrinsics: pass ``camera=``, or the Freiburg 1/2/3 presets are picked from the folder name
(``freiburg1``/``fr1`` …), else the ROS default 525/525/319.5/239.5. Lens distortion is ignored
(Freiburg 3 images are already undistorted).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.datasets._common import FileSequence, image_size
from metricslam.errors import DatasetError
from metricslam.trajectory.io import read_tum, seconds_text_to_ns

log = logging.getLogger(__name__)

#: published intrinsics of the TUM RGB-D cameras at 640x480 (fx, fy, cx, cy).
TUM_INTRINSICS = {
    "fr1": (517.3, 516.5, 318.6, 255.3),
    "fr2": (520.9, 521.0, 325.1, 249.7),
    "fr3": (535.4, 539.2, 320.1, 247.6),
    "default": (525.0, 525.0, 319.5, 239.5),
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


def preset_camera(name: str, width_px: int, height_px: int) -> PinholeCamera:
    """Intrinsics preset from a folder name (``freiburg1`` / ``fr1`` …), rescaled to the image size."""
    m = re.search(r"(?:freiburg|fr)([123])", name.lower())
    fx, fy, cx, cy = TUM_INTRINSICS[f"fr{m.group(1)}" if m else "default"]
    cam = PinholeCamera(fx_px=fx, fy_px=fy, cx_px=cx, cy_px=cy, width_px=640, height_px=480)
    return cam if (width_px, height_px) == (640, 480) else cam.resized(width_px, height_px)


class TumRgbd(FileSequence):
    """A TUM RGB-D sequence as a :class:`~metricslam.datasets.base.Sequence`.

    Args:
        seq_dir: the sequence folder (holds ``rgb.txt``).
        camera: intrinsics; default from the folder name (see module doc).
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
        if camera is None:
            w, h = image_size(files[0])
            camera = preset_camera(seq_dir.name, w, h)
        super().__init__(
            name=seq_dir.name, camera=camera, baseline_m=None, image_paths=files, stamps_ns=stamps,
            depth_paths=depth_paths, depth_scale_per_m=TUM_DEPTH_SCALE_PER_M, poses_gt=poses,
            color=True,
        )
