"""Ground truth for the evaluator, from a pose file or a dataset folder in any supported layout.

``--gt`` of ``metricslam eval`` may be

=====================================  ===========================================================
a KITTI pose file                      one ``T_world_cam`` per frame, no timestamps (``times=`` or
                                       ``--gt-times times.txt`` adds them for a TUM estimate)
a TUM file                             ``t tx ty tz qx qy qz qw`` (``groundtruth.txt``)
an EuRoC ground-truth CSV              ``state_groundtruth_estimate0/data.csv``: ``T_world_body``
                                       at ns stamps; composed with ``T_BS`` of the ``cam0/sensor.yaml``
                                       beside it into ``T_world_cam`` (body poses, with a note, when
                                       there is none)
a KITTI sequence folder                its pose file (as the reader finds it) and ``times.txt``
a TUM folder                           its ``groundtruth.txt``
an EuRoC folder (or ``mav0``)          its ground-truth CSV and ``cam0/sensor.yaml``
=====================================  ===========================================================

Per-frame ground truth (KITTI) pairs with a KITTI estimate line by line; time-stamped ground
truth pairs with a TUM estimate by nearest timestamp (:mod:`metricslam.evaluation.associate`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from metricslam.errors import TrajectoryError
from metricslam.trajectory.io import read_trajectory


@dataclass(frozen=True)
class GroundTruth:
    """Poses to evaluate against.

    Attributes:
        T_world_cam: (N, 4, 4) camera poses.
        t_ns: (N,) int64 stamps, or None (KITTI file without ``times``).
        per_frame: one pose per input frame (KITTI): a KITTI estimate pairs with it by line.
        notes: what the reader had to assume (reported with the metrics).
    """

    T_world_cam: np.ndarray
    t_ns: np.ndarray | None
    per_frame: bool
    notes: list[str] = field(default_factory=list)


def read_ground_truth(path: str | Path, fmt: str = "auto", times: str | Path | None = None) -> GroundTruth:
    """Ground truth from a file or a dataset folder (module docstring).

    Args:
        path: the file or folder.
        fmt: ``auto``, ``kitti``, ``tum`` or ``euroc`` for a file (folders are detected).
        times: a KITTI ``times.txt`` (seconds, one line per pose) for a KITTI pose file.

    Raises:
        TrajectoryError: missing or malformed files (naming file and line).
    """
    path = Path(path)
    if path.is_dir():
        return _from_folder(path)
    if fmt == "euroc" or (fmt == "auto" and _looks_like_euroc_csv(path)):
        return _from_euroc_csv(path)
    t_ns, T = read_trajectory(path, fmt)
    if t_ns is not None:
        return GroundTruth(T, t_ns, per_frame=False)
    return GroundTruth(T, _kitti_times(Path(times), T.shape[0]) if times is not None else None, per_frame=True)


def _kitti_times(path: Path, n: int) -> np.ndarray:
    from metricslam.datasets.kitti import read_times
    from metricslam.errors import DatasetError

    if not path.is_file():
        raise TrajectoryError("times file does not exist (expected KITTI times.txt, seconds)", path)
    try:
        return read_times(path, n)
    except DatasetError as exc:
        raise TrajectoryError(str(exc)) from None


def _from_folder(path: Path) -> GroundTruth:
    from metricslam.datasets import detect_format
    from metricslam.errors import DatasetError

    try:
        fmt = detect_format(path)
    except DatasetError:
        fmt = None
    if fmt == "tum" or (path / "groundtruth.txt").is_file():
        t_ns, T = read_trajectory(path / "groundtruth.txt", "tum")
        return GroundTruth(T, t_ns, per_frame=False)
    if fmt == "euroc" or (path / "state_groundtruth_estimate0").is_dir():
        from metricslam.datasets.euroc import mav0_dir

        return _from_euroc_csv(mav0_dir(path) / "state_groundtruth_estimate0" / "data.csv")
    if fmt == "kitti":
        from metricslam.datasets.kitti import find_poses_file

        poses = find_poses_file(path)
        if poses is None:
            raise TrajectoryError("no ground-truth pose file for this KITTI folder (poses/*.txt inside, "
                                  "or ../../poses/<name>.txt)", path)
        times = path / "times.txt"
        return read_ground_truth(poses, "kitti", times if times.is_file() else None)
    raise TrajectoryError("not a folder with ground truth: expected a KITTI sequence (image_0/), a TUM "
                          "folder (groundtruth.txt) or an EuRoC folder (mav0/)", path)


def _looks_like_euroc_csv(path: Path) -> bool:
    """A comma-separated file whose first data line starts with an integer ns stamp and has at
    least 8 columns (EuRoC's ground truth has 17)."""
    try:
        with path.open() as f:
            for line in f:
                text = line.strip()
                if text and not text.startswith("#"):
                    parts = text.split(",")
                    return len(parts) >= 8 and parts[0].strip().isdigit()
    except (OSError, UnicodeDecodeError):
        return False
    return False


def _from_euroc_csv(path: Path) -> GroundTruth:
    from metricslam.datasets.euroc import read_groundtruth, read_sensor_yaml

    if not path.is_file():
        raise TrajectoryError("EuRoC ground-truth file does not exist", path)
    t_ns, T_world_body = read_groundtruth(path)
    sensor = path.parent.parent / "cam0" / "sensor.yaml"
    if sensor.is_file():
        _, T_body_cam = read_sensor_yaml(sensor)
        return GroundTruth(T_world_body @ T_body_cam, t_ns, per_frame=False)
    return GroundTruth(T_world_body, t_ns, per_frame=False, notes=[
        f"no {sensor} beside the EuRoC ground truth: compared body poses with camera poses "
        "(ATE/RPE include the body-camera lever arm)"])
