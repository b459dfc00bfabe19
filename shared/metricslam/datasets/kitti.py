"""KITTI odometry reader (also reads what the synthetic generator writes in the same layout).

Layout of a sequence folder ``SEQ``::

    SEQ/image_0/000000.png …    left gray images (required; .png, or .jpg/.jpeg)
    SEQ/image_1/000000.png …    right gray images (optional; stereo; same names as image_0)
    SEQ/calib.txt               "P0: 12 numbers" … "P3: …" (3x4 projections, row-major)
    SEQ/times.txt               one timestamp in seconds per image (optional: 10 Hz assumed)
    SEQ/depth_0/000000.png …    optional uint16 depth, metres × 256, 0 = none
    ground truth, first found:  poses_file argument; SEQ/poses/*.txt if exactly one;
                                SEQ/../../poses/<SEQ name>.txt (the official tree)

Ground truth is ``T_world_cam0`` per line (3x4 row-major). The camera comes from P0; the stereo
baseline from P1: ``baseline_m = (P0[0,3] − P1[0,3]) / fx``. See ``docs/conventions.md``.
"""

from __future__ import annotations

import logging
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
from metricslam.errors import CalibrationError, DatasetError, TrajectoryError
from metricslam.trajectory.io import read_kitti_poses, seconds_text_to_ns

log = logging.getLogger(__name__)


def read_kitti_calib(path: Path) -> dict[str, np.ndarray]:
    """``calib.txt`` -> ``{"P0": (3, 4), …}``; other keys (``Tr``) are kept as flat arrays.

    Raises:
        CalibrationError: missing file, a line without ``KEY:``, a P line without 12 numbers,
            or no P0.
    """
    if not path.is_file():
        raise CalibrationError("calibration file does not exist (expected P0..P3 lines)", path)
    out: dict[str, np.ndarray] = {}
    for line_no, raw in enumerate(path.read_text().splitlines(), start=1):
        text = raw.strip()
        if not text or text.startswith("#"):
            continue
        if ":" not in text:
            raise CalibrationError(f"expected 'KEY: numbers', got {text[:40]!r}", path, line_no)
        key, values = text.split(":", 1)
        key = key.strip()
        if key.startswith("P") and key[1:].isdigit():
            out[key] = read_float_fields(values, 12, path, line_no, f"{key} as a 3x4 matrix",
                                         CalibrationError).reshape(3, 4)
        else:
            out[key] = read_float_fields(values, None, path, line_no, key, CalibrationError)
    if "P0" not in out:
        raise CalibrationError("no 'P0:' line (the left camera's 3x4 projection)", path)
    return out


def read_times(path: Path, n_images: int) -> np.ndarray:
    """``times.txt`` (seconds, one per image) -> (N,) int64 ns."""
    lines = [(i, s.strip()) for i, s in enumerate(path.read_text().splitlines(), 1) if s.strip()]
    if len(lines) != n_images:
        raise DatasetError(
            f"has {len(lines)} timestamps but there are {n_images} images; expected one per image",
            path,
        )
    stamps = []
    for line_no, text in lines:
        try:
            stamps.append(seconds_text_to_ns(text.split()[0], path, line_no))
        except TrajectoryError as exc:
            raise DatasetError(f"expected a timestamp in seconds, got {text!r}", path, line_no) from exc
    t = np.asarray(stamps, dtype=np.int64)
    bad = np.nonzero(np.diff(t) <= 0)[0]
    if bad.size:
        raise DatasetError("timestamps must increase strictly", path, int(lines[bad[0] + 1][0]))
    return t


def find_poses_file(seq_dir: Path) -> Path | None:
    """``seq_dir/poses/*.txt`` if exactly one, else ``seq_dir/../../poses/<name>.txt``, else None."""
    local = sorted((seq_dir / "poses").glob("*.txt")) if (seq_dir / "poses").is_dir() else []
    if len(local) == 1:
        return local[0]
    if len(local) > 1:
        raise DatasetError(
            f"{len(local)} pose files in {seq_dir / 'poses'}; pass poses_file= to pick one"
        )
    official = seq_dir.parent.parent / "poses" / f"{seq_dir.name}.txt"
    return official if official.is_file() else None


class KittiOdometry(FileSequence):
    """A KITTI odometry sequence folder as a :class:`~metricslam.datasets.base.Sequence`.

    Args:
        seq_dir: the sequence folder (``…/sequences/07``).
        poses_file: ground-truth pose file; default: found as described in the module doc.
        load_right: load ``image_1`` as the right stereo image when it exists.
        load_depth: load ``depth_0`` PNGs into ``Frame.depth_m`` when they exist.
        calibration: left-camera intrinsics (and distortion, undone at load) to use instead of
            P0 (``run --calib``, :mod:`metricslam.calibration`); the stereo baseline still
            comes from P1.
    """

    def __init__(
        self,
        seq_dir: str | Path,
        poses_file: str | Path | None = None,
        load_right: bool = True,
        load_depth: bool = True,
        calibration: Calibration | None = None,
    ) -> None:
        seq_dir = Path(seq_dir)
        if not seq_dir.is_dir():
            raise DatasetError("KITTI sequence folder does not exist", seq_dir)
        images = list_images(seq_dir / "image_0")
        calib_path = seq_dir / "calib.txt"
        calib = read_kitti_calib(calib_path)
        w, h = image_size(images[0])
        P0 = calib["P0"]
        camera, maps = reader_camera(calibration, P0, w, h, calib_path)
        times = seq_dir / "times.txt"
        if times.is_file():
            stamps = read_times(times, len(images))
        else:
            log.warning("%s: no times.txt, assuming 10 Hz", seq_dir)
            stamps = np.arange(len(images), dtype=np.int64) * NOMINAL_PERIOD_NS

        right_paths = None
        baseline_m = None
        if load_right and (seq_dir / "image_1").is_dir():
            right_paths = _matching(images, seq_dir / "image_1", required=True)
            if "P1" not in calib:
                raise CalibrationError("image_1/ exists but calib has no 'P1:' line", calib_path)
            baseline_m = float((P0[0, 3] - calib["P1"][0, 3]) / calib["P1"][0, 0])
            if not baseline_m > 0:
                raise CalibrationError(
                    f"P1 gives baseline {baseline_m:.4f} m; expected the right camera at +x "
                    "(P1[0,3] = -fx·baseline < 0)", calib_path,
                )
        depth_paths = None
        if load_depth and (seq_dir / "depth_0").is_dir():
            depth_paths = _matching(images, seq_dir / "depth_0", required=False, suffix=".png")

        poses = None
        pf = Path(poses_file) if poses_file is not None else find_poses_file(seq_dir)
        if pf is not None:
            poses = read_kitti_poses(pf)
            if poses.shape[0] != len(images):
                raise TrajectoryError(
                    f"has {poses.shape[0]} poses but {seq_dir / 'image_0'} has {len(images)} "
                    "images; expected one pose per image", pf,
                )
        super().__init__(
            name=seq_dir.name, camera=camera, baseline_m=baseline_m, image_paths=images,
            stamps_ns=stamps, right_paths=right_paths, depth_paths=depth_paths,
            depth_scale_per_m=256.0, poses_gt=poses, color=False, undistort_maps=maps,
        )
        self.calib = calib
        self.seq_dir = seq_dir


def _matching(images: list[Path], folder: Path, required: bool, suffix: str | None = None) -> list:
    """Files in ``folder`` with the same names as ``images`` (None where missing if not required).

    ``suffix`` replaces the image's extension (depth maps are always ``.png``, even beside JPEG
    frames); None keeps it (a right ``.jpg`` partners a left ``.jpg``).
    """
    out = []
    for p in images:
        q = folder / (p.name if suffix is None else p.stem + suffix)
        if not q.is_file():
            if required:
                raise DatasetError(f"missing {p.name} (every left image needs a partner here)", folder)
            q = None
        out.append(q)
    return out
