"""EuRoC MAV (ASL folder format) reader: ``cam0`` images, intrinsics, body→camera extrinsics,
ground truth from ``state_groundtruth_estimate0`` converted to ``T_world_cam``.

Layout (``ROOT`` is the sequence folder holding ``mav0/``, or ``mav0`` itself)::

    mav0/cam0/data.csv                         "#timestamp [ns],filename"
    mav0/cam0/data/<t_ns>.png                  gray images (distorted, radial-tangential)
    mav0/cam0/sensor.yaml                      intrinsics [fu, fv, cu, cv], resolution,
                                               distortion_coefficients, T_BS (body→sensor,
                                               i.e. T_body_cam: p_body = T_BS·p_cam)
    mav0/state_groundtruth_estimate0/data.csv  t_ns, p_RS_R (xyz), q_RS (w x y z), …

Images are undistorted on load (``undistort=True``, same K), so ``camera`` is an exact pinhole
model; ``sensor.yaml`` is read by :mod:`metricslam.calibration` (radial-tangential or
equidistant distortion), and ``calibration=`` (``run --calib``) replaces its intrinsics. Ground truth ``T_world_body`` is interpolated to each image time (linear position, slerp
rotation) and composed ``T_world_cam = T_world_body @ T_body_cam``. Frames outside the ground-truth
time span are dropped (``trim_to_groundtruth=True``) so every frame has a pose. Stereo (cam1) is
not rectified in EuRoC and is not read.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from metricslam.calibration import (
    Calibration,
    calibration_from_document,
    camera_and_maps,
    numbers,
    read_yaml_document,
)
from metricslam.datasets._common import FileSequence, image_size, read_float_fields
from metricslam.errors import CalibrationError, DatasetError, GeometryError, TrajectoryError

log = logging.getLogger(__name__)


def mav0_dir(root: Path) -> Path:
    """``root/mav0`` or ``root`` itself if it already is the ``mav0`` folder."""
    if (root / "mav0").is_dir():
        return root / "mav0"
    if (root / "cam0").is_dir():
        return root
    raise DatasetError("not an EuRoC folder: expected mav0/cam0/ inside", root)


def read_sensor_yaml(path: Path) -> tuple[Calibration, np.ndarray]:
    """``sensor.yaml`` -> ``(calibration, T_body_cam (4, 4))``: intrinsics, resolution and
    distortion through :func:`metricslam.calibration.calibration_from_document` (the one
    calibration loader), ``T_BS`` here."""
    doc = read_yaml_document(path)
    calib = calibration_from_document(doc, path)
    T = numbers(doc, "T_BS", 16, path).reshape(4, 4)
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise CalibrationError("T_BS is not a rigid 4x4 transform", path)
    return calib, T


def read_image_list(path: Path, image_dir: Path) -> tuple[np.ndarray, list[Path]]:
    """``data.csv`` ("t_ns,filename") -> ``(t_ns (N,), image paths)``."""
    if not path.is_file():
        raise DatasetError("image list data.csv does not exist", path)
    stamps, files = [], []
    for line_no, raw in enumerate(path.read_text().splitlines(), start=1):
        text = raw.strip()
        if not text or text.startswith("#"):
            continue
        parts = [p.strip() for p in text.split(",")]
        if len(parts) != 2 or not parts[0].isdigit():
            raise DatasetError(f"expected 'timestamp_ns,filename', got {text[:60]!r}", path, line_no)
        stamps.append(int(parts[0]))
        files.append(image_dir / parts[1])
    if not files:
        raise DatasetError("lists no images", path)
    t = np.asarray(stamps, dtype=np.int64)
    if np.any(np.diff(t) <= 0):
        raise DatasetError("timestamps must increase strictly", path)
    return t, files


def read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``state_groundtruth_estimate0/data.csv`` -> ``(t_ns (M,), T_world_body (M, 4, 4))``."""
    from metricslam.geometry import so3

    stamps, poses = [], []
    for line_no, raw in enumerate(path.read_text().splitlines(), start=1):
        text = raw.strip()
        if not text or text.startswith("#"):
            continue
        first, _, rest = text.partition(",")
        if not first.strip().isdigit():
            raise TrajectoryError(f"expected an integer ns timestamp first, got {first!r}", path, line_no)
        v = read_float_fields(rest, None, path, line_no,
                              "p_RS_R x y z, q_RS w x y z, …", TrajectoryError)
        if v.size < 7:
            raise TrajectoryError(f"expected at least 8 columns (t, p xyz, q wxyz), got {v.size + 1}",
                                  path, line_no)
        T = np.eye(4)
        try:
            T[:3, :3] = so3.from_quat_xyzw(np.array([v[4], v[5], v[6], v[3]]))
        except GeometryError as exc:
            raise TrajectoryError(f"bad quaternion: {exc}", path, line_no) from None
        T[:3, 3] = v[:3]
        stamps.append(int(first))
        poses.append(T)
    if not poses:
        raise TrajectoryError("ground-truth file holds no poses", path)
    t = np.asarray(stamps, dtype=np.int64)
    if np.any(np.diff(t) <= 0):
        raise TrajectoryError("ground-truth timestamps must increase strictly", path)
    return t, np.stack(poses)


def interpolate_poses(t_ns_src: np.ndarray, T_src: np.ndarray, t_ns_query: np.ndarray) -> np.ndarray:
    """Poses at query times inside ``[t_src[0], t_src[-1]]``: linear position, slerp rotation."""
    from scipy.spatial.transform import Rotation, Slerp

    t0 = t_ns_src[0]
    ts = (t_ns_src - t0).astype(np.float64)
    tq = (np.asarray(t_ns_query) - t0).astype(np.float64)
    out = np.tile(np.eye(4), (tq.shape[0], 1, 1))
    out[:, :3, :3] = Slerp(ts, Rotation.from_matrix(T_src[:, :3, :3]))(tq).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(tq, ts, T_src[:, k, 3])
    return out


class EuRoC(FileSequence):
    """A EuRoC MAV sequence (``cam0``) as a :class:`~metricslam.datasets.base.Sequence`.

    Args:
        root: the sequence folder (holding ``mav0/``) or the ``mav0`` folder.
        undistort: remap images to the undistorted pinhole model with the same K.
        trim_to_groundtruth: drop frames outside the ground-truth time span (when GT exists).
        calibration: intrinsics and distortion to use instead of ``sensor.yaml``'s (``run
            --calib``); ``T_BS`` still comes from ``sensor.yaml``.
    """

    def __init__(self, root: str | Path, undistort: bool = True, trim_to_groundtruth: bool = True,
                 calibration: Calibration | None = None) -> None:
        root = Path(root)
        mav0 = mav0_dir(root)
        cam = mav0 / "cam0"
        sensor_calib, T_body_cam = read_sensor_yaml(cam / "sensor.yaml")
        stamps, files = read_image_list(cam / "data.csv", cam / "data")
        if calibration is not None:
            log.info("%s: intrinsics from %s instead of sensor.yaml", root, calibration.source)
            sensor_calib = calibration.for_image(*image_size(files[0]))
        poses = None
        gt_path = mav0 / "state_groundtruth_estimate0" / "data.csv"
        if gt_path.is_file():
            t_gt, T_world_body = read_groundtruth(gt_path)
            inside = (stamps >= t_gt[0]) & (stamps <= t_gt[-1])
            if not inside.any():
                raise TrajectoryError("ground truth does not overlap the image timestamps", gt_path)
            if trim_to_groundtruth and not inside.all():
                log.info("%s: dropping %d frames outside the ground-truth span", root, (~inside).sum())
                stamps = stamps[inside]
                files = [f for f, keep in zip(files, inside) if keep]
            if trim_to_groundtruth or inside.all():
                poses = interpolate_poses(t_gt, T_world_body, stamps) @ T_body_cam
        camera, maps = camera_and_maps(sensor_calib, sensor_calib.camera.width_px,
                                       sensor_calib.camera.height_px)
        super().__init__(
            name=root.name if root.name != "mav0" else root.parent.name, camera=camera,
            baseline_m=None, image_paths=files, stamps_ns=stamps, poses_gt=poses, color=False,
            undistort_maps=maps if undistort else None,
        )
        self.T_body_cam = T_body_cam
        self.calibration = sensor_calib
        self.distortion = np.asarray(sensor_calib.distortion_coefficients)
