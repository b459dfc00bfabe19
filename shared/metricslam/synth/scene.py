"""A synthetic stereo scene: world + trajectory + cameras, rendered frame by frame in memory.

Use :func:`metricslam.synth.generate_sequence` to write a KITTI-layout folder; use
:class:`SynthScene` directly (tests, training) to get arrays without touching the disk.
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from metricslam.camera import PinholeCamera
from metricslam.errors import SynthError
from metricslam.synth import trajectory as trj
from metricslam.synth.photometric import PhotometricConfig, blur_poses, exposure_gains, to_uint8
from metricslam.synth.render import Renderer
from metricslam.synth.textures import build_atlas
from metricslam.synth.world import WorldConfig, build_world

# KITTI odometry 00-02 left gray camera at 1241x376
_KITTI_FX_PX, _KITTI_CX_PX, _KITTI_CY_PX = 718.856, 607.1928, 185.2157
_KITTI_SIZE = (1241, 376)


def kitti_like_camera(width_px: int = 1241, height_px: int = 376,
                      fx_px: float | None = None) -> PinholeCamera:
    """KITTI 00 intrinsics scaled to ``width × height`` (square pixels, focal scales with width).

    ``fx_px`` (px at ``width_px``, ``fy = fx``) replaces the scaled KITTI focal length (718.856 px
    at 1241 wide) for another rig's field of view; the principal point stays KITTI's, scaled.
    """
    if width_px < 16 or height_px < 16:
        raise SynthError(f"image size {width_px}x{height_px} is too small; use at least 16x16")
    if fx_px is not None and not fx_px > 0:
        raise SynthError(f"focal length must be > 0 px, got {fx_px} (--fx)")
    s = width_px / _KITTI_SIZE[0]
    f = _KITTI_FX_PX * s if fx_px is None else float(fx_px)
    return PinholeCamera(fx_px=f, fy_px=f,
                         cx_px=(_KITTI_CX_PX + 0.5) * s - 0.5,
                         cy_px=(_KITTI_CY_PX + 0.5) * height_px / _KITTI_SIZE[1] - 0.5,
                         width_px=width_px, height_px=height_px)


class SynthConfig(BaseModel):
    """Everything that defines a synthetic sequence besides the seed and the trajectory."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    width_px: int = Field(1241, ge=16)
    height_px: int = Field(376, ge=16)
    #: focal length (px at ``width_px``, fx = fy); None: KITTI 00's scaled to the width
    fx_px: float | None = Field(None, gt=0)
    #: stereo baseline (m): the right camera sits at +x by this much
    baseline_m: float = Field(0.54, gt=0)
    frame_rate_hz: float = Field(trj.FRAME_RATE_HZ, gt=0)
    far_m: float = Field(250.0, gt=1, le=255.0)
    world: WorldConfig = WorldConfig()
    photometric: PhotometricConfig = PhotometricConfig()


@dataclass(frozen=True)
class StereoFrame:
    """One rendered frame.

    Attributes:
        left, right: (H, W) uint8 gray images (right camera at +x by the baseline).
        depth_m: (H, W) float32 depth of the left image along z, metres, 0 = sky/none.
        T_world_cam: (4, 4) pose of the left camera.
    """

    left: np.ndarray
    right: np.ndarray
    depth_m: np.ndarray
    T_world_cam: np.ndarray


class SynthScene:
    """A seeded street world along ``T_world_cam`` (N, 4, 4) with a stereo rig: KITTI-like by
    default; ``config.fx_px``, ``config.baseline_m`` and ``config.world.camera_height_m`` change
    its focal length, baseline and mounting height."""

    def __init__(self, T_world_cam: np.ndarray, seed: int, config: SynthConfig | None = None) -> None:
        self.config = config or SynthConfig()
        self.seed = int(seed)
        self.T_world_cam = np.asarray(T_world_cam, float)
        if self.T_world_cam.ndim != 3 or self.T_world_cam.shape[1:] != (4, 4):
            raise SynthError(f"expected poses of shape (N, 4, 4), got {self.T_world_cam.shape}")
        cfg = self.config
        self.camera = kitti_like_camera(cfg.width_px, cfg.height_px, cfg.fx_px)
        self.world = build_world(self.T_world_cam, self.seed, cfg.world)
        self.renderer = Renderer(self.world, self.camera, build_atlas(self.seed), far_m=cfg.far_m)
        self.gains = exposure_gains(len(self.T_world_cam), self.seed, cfg.photometric)
        self.T_cam0_cam1 = np.eye(4)
        self.T_cam0_cam1[0, 3] = cfg.baseline_m

    @classmethod
    def procedural(cls, frames: int, seed: int, path: str = "loop",
                   config: SynthConfig | None = None) -> "SynthScene":
        return cls(trj.procedural(path, frames, seed), seed, config)

    def __len__(self) -> int:
        return len(self.T_world_cam)

    def _radiance(self, T_world_cam0: np.ndarray, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        poses = blur_poses(self.T_world_cam, index, self.config.photometric)
        if len(poses) == 1:
            poses = [T_world_cam0]
        left = right = None
        depth = None
        for T in poses:
            rl, d = self.renderer.render(T)
            rr, _ = self.renderer.render(T @ self.T_cam0_cam1)
            left = rl if left is None else left + rl
            right = rr if right is None else right + rr
        _, depth = self.renderer.render(T_world_cam0) if len(poses) > 1 else (None, d)
        return left / len(poses), right / len(poses), depth

    def frame(self, index: int) -> StereoFrame:
        """Render frame ``index`` (deterministic: same seed and index give identical bytes)."""
        if not 0 <= index < len(self):
            raise SynthError(f"frame index {index} out of range 0..{len(self) - 1}")
        T = self.T_world_cam[index]
        rad_l, rad_r, depth = self._radiance(T, index)
        pc = self.config.photometric
        rng = np.random.default_rng([self.seed, 11, index])
        g = float(self.gains[index])
        left = to_uint8(rad_l, g, rng, pc)
        right = to_uint8(rad_r, g * pc.right_gain, rng, pc)
        return StereoFrame(left, right, depth, T)


def generate_sequence(out_dir: str | Path, frames: int, seed: int, trajectory: str | Path | None = None,
                      size: tuple[int, int] = _KITTI_SIZE, start: int = 0, path: str = "loop",
                      config: SynthConfig | None = None, progress: bool = False) -> SynthScene:
    """Write a synthetic stereo sequence in KITTI odometry layout to ``out_dir``.

    Args:
        out_dir: output folder (created; its ``image_0/`` must be empty or absent).
        frames: number of frames (10 Hz).
        seed: world, trajectory and noise seed; the output is byte-identical for a seed.
        trajectory: a KITTI pose file to drive along (frames ``start .. start+frames-1``,
            rebased so the first is the identity); None uses the procedural ``path``.
        size: (width, height) in pixels.
        path: ``straight``, ``turns`` or ``loop`` (procedural trajectories only).
        config: everything else; ``size`` overrides its image size.
        progress: show a tqdm progress bar.

    Returns:
        The :class:`SynthScene` that was rendered.
    """
    from metricslam.synth.writer import KittiWriter

    if frames < 1:
        raise SynthError(f"--frames must be >= 1, got {frames}")
    if start and trajectory is None:
        raise SynthError("--start only applies to --trajectory (a KITTI pose file)")
    width, height = (int(v) for v in size)
    if width < 16 or height < 16:
        raise SynthError(f"image size {width}x{height} is too small; use at least 16x16 (--size)")
    cfg = (config or SynthConfig()).model_copy(update={"width_px": width, "height_px": height})
    T = (trj.kitti_segment(trajectory, frames, start) if trajectory is not None
         else trj.procedural(path, frames, seed))
    scene = SynthScene(T, seed, cfg)
    writer = KittiWriter(out_dir, scene.camera, cfg.baseline_m)
    indices = range(frames)
    if progress:
        from tqdm import tqdm

        indices = tqdm(indices, desc="synth", unit="frame")
    # PNG encoding (OpenCV releases the GIL) overlaps with rendering the next frame
    with ThreadPoolExecutor(max_workers=2) as pool:
        pending: deque[Future] = deque()
        for i in indices:
            f = scene.frame(i)
            pending.append(pool.submit(writer.write_frame, i, f.left, f.right, f.depth_m))
            while len(pending) > 3:
                pending.popleft().result()
        for fut in pending:
            fut.result()
    writer.finish(T, cfg.frame_rate_hz)
    return scene
