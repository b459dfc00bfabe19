"""Helpers shared by the dataset readers: lazy image loading and a list-backed sequence.

Frames are built on access (:meth:`FileSequence.__getitem__`), so opening a sequence reads only
its text files and one image header.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.datasets.base import Frame
from metricslam.errors import DatasetError

#: nominal frame period used when a sequence has no timestamps (KITTI: 10 Hz).
NOMINAL_PERIOD_NS = 100_000_000


def load_image(path: Path, color: bool) -> np.ndarray:
    """Read an 8-bit image: (H, W) uint8 gray, or (H, W, 3) uint8 RGB when ``color``."""
    import cv2

    flags = cv2.IMREAD_COLOR if color else cv2.IMREAD_GRAYSCALE
    img = cv2.imread(str(path), flags)
    if img is None:
        raise DatasetError("cannot read image (missing, truncated or not an image file)", path)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if color else img


def load_depth_png(path: Path, scale_per_m: float) -> np.ndarray:
    """Read a uint16 depth PNG: (H, W) float32 metres = value / ``scale_per_m``, 0 = no depth.

    KITTI encodes metres × 256, TUM metres × 5000.
    """
    import cv2

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DatasetError("cannot read depth PNG (missing, truncated or not an image)", path)
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise DatasetError(
            f"expected a single-channel uint16 depth PNG, got {raw.dtype} with shape {raw.shape}",
            path,
        )
    return (raw.astype(np.float32) / np.float32(scale_per_m)).astype(np.float32)


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image; reads only the header for PNGs."""
    try:
        with path.open("rb") as f:
            head = f.read(24)
    except OSError as exc:
        raise DatasetError(f"cannot open image: {exc}", path) from None
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        w, h = struct.unpack(">II", head[16:24])
        return int(w), int(h)
    img = load_image(path, color=False)
    return int(img.shape[1]), int(img.shape[0])


#: extensions of the image files a sequence folder may hold (case-insensitive)
IMAGE_EXTS: tuple[str, ...] = (".png", ".jpg", ".jpeg")


def list_images(folder: Path, exts: tuple[str, ...] = IMAGE_EXTS) -> list[Path]:
    """Image files in ``folder`` sorted by name; raises if the folder is missing or empty."""
    if not folder.is_dir():
        raise DatasetError("image folder does not exist", folder)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in exts)
    if not files:
        raise DatasetError(f"no {'/'.join(exts)} images in folder", folder)
    return files


@dataclass(eq=False)
class FileSequence:
    """A :class:`~metricslam.datasets.base.Sequence` backed by lists of files.

    Attributes:
        name: sequence name (folder name).
        camera: intrinsics of the left images.
        baseline_m: stereo baseline in metres, or None.
        image_paths: N left image files.
        stamps_ns: (N,) int64 timestamps.
        right_paths: N right image files, or None.
        depth_paths: N depth PNGs (None entries where missing), or None.
        depth_scale_per_m: PNG value per metre of depth (256 KITTI, 5000 TUM).
        poses_gt: (N, 4, 4) ground-truth ``T_world_cam``, or None.
        color: load the left/right images as RGB (else gray).
        undistort_maps: optional ``(map1, map2)`` for ``cv2.remap`` applied to every image (and,
            nearest-neighbour, to the depth maps), e.g.
            :meth:`metricslam.calibration.Calibration.undistort_maps`.
    """

    name: str
    camera: PinholeCamera
    baseline_m: float | None
    image_paths: list[Path]
    stamps_ns: np.ndarray
    right_paths: list[Path] | None = None
    depth_paths: list[Path | None] | None = None
    depth_scale_per_m: float = 256.0
    poses_gt: np.ndarray | None = None
    color: bool = False
    undistort_maps: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        n = len(self.image_paths)
        self.stamps_ns = np.asarray(self.stamps_ns, dtype=np.int64)
        if self.stamps_ns.shape != (n,):
            raise DatasetError(f"{self.name}: {self.stamps_ns.shape[0]} timestamps for {n} images")
        if self.poses_gt is not None and self.poses_gt.shape != (n, 4, 4):
            raise DatasetError(f"{self.name}: {self.poses_gt.shape[0]} poses for {n} images")

    def __len__(self) -> int:
        return len(self.image_paths)

    def __getitem__(self, index: int) -> Frame:
        return self.frame(index)

    def frame(self, index: int, extras: bool = True) -> Frame:
        """Frame ``index``; ``extras=False`` leaves out the right image and the ground-truth
        depth (``image_right``, ``baseline_m``, ``depth_m`` None), which no estimator reads
        (decoding them cost ``metricslam run`` as much as the left image: bench/results/profile.md)."""
        n = len(self)
        if not isinstance(index, (int, np.integer)):
            raise TypeError(f"frame index must be an int, got {type(index).__name__}")
        if index < 0:
            index += n
        if not 0 <= index < n:
            raise IndexError(f"frame {index} out of range for {n} frames")
        index = int(index)
        image = self._image(self.image_paths[index])
        right = self._image(self.right_paths[index]) if extras and self.right_paths is not None else None
        depth = None
        if extras and self.depth_paths is not None and self.depth_paths[index] is not None:
            depth = load_depth_png(self.depth_paths[index], self.depth_scale_per_m)
            if self.undistort_maps is not None:  # keep the ground truth registered to the image
                import cv2

                depth = cv2.remap(depth, *self.undistort_maps, interpolation=cv2.INTER_NEAREST)
        return Frame(
            index=index,
            t_ns=int(self.stamps_ns[index]),
            image=image,
            camera=self.camera,
            image_right=right,
            baseline_m=self.baseline_m if right is not None else None,
            T_world_cam=None if self.poses_gt is None else self.poses_gt[index].copy(),
            depth_m=depth,
        )

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    @property
    def t_ns(self) -> np.ndarray:
        """Timestamps (N,) int64 nanoseconds."""
        return self.stamps_ns.copy()

    @property
    def T_world_cam_gt(self) -> np.ndarray | None:
        """Ground-truth poses (N, 4, 4) of the left camera, or None."""
        return None if self.poses_gt is None else self.poses_gt.copy()

    def _image(self, path: Path) -> np.ndarray:
        img = load_image(path, self.color)
        if (img.shape[1], img.shape[0]) != (self.camera.width_px, self.camera.height_px):
            raise DatasetError(
                f"image is {img.shape[1]}x{img.shape[0]} but the sequence camera is "
                f"{self.camera.width_px}x{self.camera.height_px}; all frames must have one size",
                path,
            )
        if self.undistort_maps is not None:
            import cv2

            img = cv2.remap(img, *self.undistort_maps, interpolation=cv2.INTER_LINEAR)
        return img


def read_float_fields(
    text: str, n: int | None, path: Path, line: int | None, what: str,
    error: type[DatasetError] = DatasetError,
) -> np.ndarray:
    """Parse whitespace/comma-separated floats; raises ``error`` naming ``what`` on bad input."""
    fields = text.replace(",", " ").split()
    if n is not None and len(fields) != n:
        raise error(f"expected {n} numbers ({what}), got {len(fields)}", path, line)
    try:
        values = np.array([float(v) for v in fields], dtype=float)
    except ValueError:
        raise error(f"expected numbers ({what}), got {text.strip()!r}", path, line) from None
    if not np.all(np.isfinite(values)):
        raise error(f"{what} contains NaN or inf", path, line)
    return values
