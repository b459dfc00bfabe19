"""Dataset readers behind one interface (:class:`~metricslam.datasets.base.Sequence`).

``open_sequence(path)`` detects the format from the folder's contents:

===================  ===========================================  ==========================
format               detected by                                  reader
===================  ===========================================  ==========================
KITTI odometry       ``image_0/``                                 :class:`KittiOdometry`
KITTI raw + LiDAR    ``image_02/`` and ``depth_02/``              :class:`KittiRawDepth`
EuRoC MAV            ``mav0/`` (or ``cam0/data.csv``)             :class:`EuRoC`
TUM RGB-D            ``rgb.txt``                                  :class:`TumRgbd`
===================  ===========================================  ==========================
"""

from __future__ import annotations

from pathlib import Path

from metricslam.datasets._common import load_image
from metricslam.datasets.base import Frame, Sequence
from metricslam.datasets.euroc import EuRoC
from metricslam.datasets.kitti import KittiOdometry
from metricslam.datasets.kitti_depth import KittiRawDepth
from metricslam.datasets.tum import TumRgbd
from metricslam.errors import DatasetError

__all__ = ["EuRoC", "Frame", "KittiOdometry", "KittiRawDepth", "Sequence", "TumRgbd",
           "detect_format", "load_image", "open_sequence"]

READERS = {"kitti": KittiOdometry, "kitti_raw_depth": KittiRawDepth, "euroc": EuRoC, "tum": TumRgbd}


def detect_format(path: str | Path) -> str:
    """One of :data:`READERS`' keys for a sequence folder.

    Raises:
        DatasetError: the folder does not exist or matches no known layout.
    """
    p = Path(path)
    if not p.is_dir():
        raise DatasetError("sequence folder does not exist", p)
    if (p / "image_0").is_dir():
        return "kitti"
    if (p / "image_02").is_dir() and (p / "depth_02").is_dir():
        return "kitti_raw_depth"
    if (p / "mav0").is_dir() or (p / "cam0" / "data.csv").is_file():
        return "euroc"
    if (p / "rgb.txt").is_file():
        return "tum"
    raise DatasetError(
        "unknown dataset layout: expected image_0/ (KITTI odometry), image_02/+depth_02/ "
        "(KITTI raw depth), mav0/ (EuRoC) or rgb.txt (TUM RGB-D)", p,
    )


def open_sequence(path: str | Path, **kw) -> Sequence:
    """Open a sequence folder with the reader its layout calls for; ``kw`` go to the reader
    (e.g. ``poses_file=``, ``load_right=`` for KITTI; ``format=`` forces a reader).

    Every reader takes ``calibration=`` (a :class:`metricslam.calibration.Calibration`, ``run
    --calib``), which replaces the intrinsics it would read or infer and is undistorted at load."""
    fmt = kw.pop("format", None) or detect_format(path)
    if fmt not in READERS:
        raise DatasetError(f"unknown format {fmt!r}; expected one of {sorted(READERS)}", path)
    return READERS[fmt](path, **kw)
