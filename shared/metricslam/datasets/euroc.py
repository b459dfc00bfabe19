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
model. Ground truth ``T_world_body`` is interpolated to each image time (linear position, slerp
rotation) and composed ``T_world_cam = T_world_body @ T_body_cam``. Frames outside the ground-truth
time span are dropped (``trim_to_groundtruth=True``) so every frame has a pose. Stereo (cam1) is
not rectified in EuRoC and is not read.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.datasets._common import FileSequence, read_float_fields
from metricslam.errors import (
    CalibrationError,
    CameraError,
    DatasetError,
    GeometryError,
    TrajectoryError,
)

log = logging.getLogger(__name__)


def mav0_dir(root: Path) -> Path:
    """``root/mav0`` or ``root`` itself if it already is the ``mav0`` folder."""
    if (root / "mav0").is_dir():
        return root / "mav0"
    if (root / "cam0").is_dir():
        return root
    raise DatasetError("not an EuRoC folder: expected mav0/cam0/ inside", root)


def read_sensor_yaml(path: Path) -> tuple[np.ndarray, tuple[int, int], np.ndarray, np.ndarray]:
    """``sensor.yaml`` -> ``(K (3,3), (width, height), distortion (4|5,), T_body_cam (4,4))``."""
    import yaml

    if not path.is_file():
        raise CalibrationError("camera sensor.yaml does not exist", path)
    text = "\n".join(line for line in path.read_text().splitlines() if not line.startswith("%"))
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        line = getattr(getattr(exc, "problem_mark", None), "line", None)
        raise CalibrationError(f"not valid YAML: {exc}", path, None if line is None else line + 1) from None
    if not isinstance(doc, dict):
        raise CalibrationError("expected a YAML mapping with intrinsics, resolution, T_BS", path)

    def numbers(key: str, n: int | tuple[int, ...]) -> np.ndarray:
        val = doc.get(key)
        if isinstance(val, dict):
            val = val.get("data")
        ns = (n,) if isinstance(n, int) else n
        try:
            arr = np.asarray(val, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise CalibrationError(f"'{key}' must be a list of numbers, got {val!r}", path) from None
        if arr.size not in ns or not np.all(np.isfinite(arr)):
            raise CalibrationError(f"'{key}' must hold {' or '.join(map(str, ns))} finite numbers, "
                                   f"got {arr.size}", path)
        return arr

    model = doc.get("camera_model", "pinhole")
    if model != "pinhole":
        raise CalibrationError(f"camera_model {model!r} is not supported; expected pinhole", path)
    fu, fv, cu, cv = numbers("intrinsics", 4)
    w, h = (int(v) for v in numbers("resolution", 2))
    dist = numbers("distortion_coefficients", (4, 5)) if "distortion_coefficients" in doc else np.zeros(4)
    dm = doc.get("distortion_model", "radial-tangential")
    if dm not in ("radial-tangential", "radtan", "plumb_bob", "none"):
        raise CalibrationError(f"distortion_model {dm!r} is not supported; expected radial-tangential", path)
    T = numbers("T_BS", 16).reshape(4, 4)
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise CalibrationError("T_BS is not a rigid 4x4 transform", path)
    K = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    return K, (w, h), dist, T


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
    """

    def __init__(self, root: str | Path, undistort: bool = True, trim_to_groundtruth: bool = True) -> None:
        root = Path(root)
        mav0 = mav0_dir(root)
        cam = mav0 / "cam0"
        K, (w, h), dist, T_body_cam = read_sensor_yaml(cam / "sensor.yaml")
        try:
            camera = PinholeCamera.from_K(K, w, h)
        except CameraError as exc:
            raise CalibrationError(f"invalid intrinsics: {exc}", cam / "sensor.yaml") from exc
        stamps, files = read_image_list(cam / "data.csv", cam / "data")
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
        maps = None
        if undistort and np.any(dist != 0):
            import cv2

            maps = cv2.initUndistortRectifyMap(K, dist, None, K, (w, h), cv2.CV_32FC1)
        super().__init__(
            name=root.name if root.name != "mav0" else root.parent.name, camera=camera,
            baseline_m=None, image_paths=files, stamps_ns=stamps, poses_gt=poses, color=False,
            undistort_maps=maps,
        )
        self.T_body_cam = T_body_cam
        self.distortion = dist
