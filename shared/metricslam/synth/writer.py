"""Writes a sequence in the KITTI odometry layout (plus ``depth_0/`` ground-truth depth).

```
OUT/image_0/NNNNNN.png   left gray uint8        OUT/calib.txt   P0..P3 (3x4 row-major)
OUT/image_1/NNNNNN.png   right gray uint8       OUT/times.txt   seconds, one per frame
OUT/depth_0/NNNNNN.png   uint16, depth_m × 256   OUT/poses/00.txt T_world_cam0, 3x4 per line
                         along z, 0 = sky/none
```
The right camera sits at +x (``baseline_m``) in the left camera frame, so ``P1[0, 3] = -fx·B``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.errors import SynthError
from metricslam.trajectory.io import write_kitti_poses

DEPTH_SCALE = 256.0  # KITTI depth encoding: uint16 = round(depth_m * 256)
MAX_DEPTH_M = 65535 / DEPTH_SCALE


def projection_matrices(camera: PinholeCamera, baseline_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(P0, P1), each (3, 4): left ``K[I|0]`` and right ``K[I|-B·x]``."""
    P0 = np.hstack([camera.K, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -camera.fx_px * baseline_m
    return P0, P1


def encode_depth(depth_m: np.ndarray) -> np.ndarray:
    """Depth (H, W) metres, 0 = none -> uint16 metres × 256 (values beyond 255.99 m -> 0)."""
    d = np.rint(np.asarray(depth_m, np.float64) * DEPTH_SCALE)
    d[(d > 65535) | ~np.isfinite(d)] = 0
    return d.astype(np.uint16)


class KittiWriter:
    """Creates ``out_dir`` in KITTI layout; call :meth:`write_frame` per frame, then
    :meth:`finish` with the poses. Refuses to write into a non-empty ``image_0/``."""

    def __init__(self, out_dir: str | Path, camera: PinholeCamera, baseline_m: float,
                 png_compression: int = 1) -> None:
        self.out = Path(out_dir)
        if (self.out / "image_0").is_dir() and any((self.out / "image_0").iterdir()):
            raise SynthError(f"{self.out / 'image_0'} is not empty; choose a new OUT_DIR or delete it")
        for sub in ("image_0", "image_1", "depth_0", "poses"):
            (self.out / sub).mkdir(parents=True, exist_ok=True)
        self.camera = camera
        self.baseline_m = float(baseline_m)
        self._png = png_compression

    def write_frame(self, index: int, left: np.ndarray, right: np.ndarray, depth_m: np.ndarray) -> None:
        """Write the uint8 gray pair and the left depth of frame ``index``."""
        import cv2

        name = f"{index:06d}.png"
        # RLE strategy: faster than the default and smaller on these images (measured)
        flags = [cv2.IMWRITE_PNG_COMPRESSION, self._png,
                 cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
        for sub, img in (("image_0", left), ("image_1", right), ("depth_0", encode_depth(depth_m))):
            if not cv2.imwrite(str(self.out / sub / name), img, flags):
                raise SynthError(f"could not write {self.out / sub / name}; check disk space")

    def finish(self, T_world_cam: np.ndarray, frame_rate_hz: float, seq_id: str = "00") -> None:
        """Write ``calib.txt``, ``times.txt`` and ``poses/<seq_id>.txt``."""
        P0, P1 = projection_matrices(self.camera, self.baseline_m)
        lines = []
        for name, P in (("P0", P0), ("P1", P1), ("P2", P0), ("P3", P1)):
            # shortest exact repr: the file parses back to exactly these doubles
            lines.append(f"{name}: " + " ".join(np.format_float_scientific(v, unique=True)
                                                 for v in P.ravel()))
        (self.out / "calib.txt").write_text("\n".join(lines) + "\n")
        times = np.arange(len(T_world_cam)) / frame_rate_hz
        (self.out / "times.txt").write_text("".join(f"{t:.6e}\n" for t in times))
        write_kitti_poses(self.out / "poses" / f"{seq_id}.txt", T_world_cam)
