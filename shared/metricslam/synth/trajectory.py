"""Camera trajectories for synthetic sequences: procedural paths and KITTI ground-truth files.

All poses are ``T_world_cam0`` (4, 4) of the left camera, camera frame x right, y down,
z forward; ``world`` is the first returned camera frame (KITTI convention), so world y points
down and the road lies at about ``y = +camera_height_m`` below the camera.
See ``docs/conventions.md``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from metricslam.errors import SynthError
from metricslam.trajectory.io import read_kitti_poses
from metricslam.geometry import se3, so3

PATH_KINDS = ("straight", "turns", "loop")
FRAME_RATE_HZ = 10.0


def rebase(T_world_cam: np.ndarray) -> np.ndarray:
    """Re-express poses (N, 4, 4) so that the first one is the identity (KITTI's world)."""
    T_first_world = se3.inverse(T_world_cam[0])
    return np.einsum("ij,njk->nik", T_first_world, T_world_cam)


def kitti_segment(path: str | Path, frames: int, start: int = 0) -> np.ndarray:
    """Frames ``start .. start+frames-1`` of a KITTI pose file, rebased to the first of them."""
    T_all = read_kitti_poses(path)
    if start < 0 or start + frames > len(T_all):
        raise SynthError(f"{path} has {len(T_all)} poses; cannot take {frames} frames from "
                         f"index {start} (lower --frames or --start)")
    return rebase(T_all[start:start + frames])


def _segments(kind: str, distance_m: float, rng: np.random.Generator) -> list[tuple[float, float]]:
    """(length_m, curvature_per_m) pieces covering ``distance_m``; curvature > 0 turns right."""
    if kind == "straight":
        return [(distance_m + 1.0, 0.0)]
    if kind == "turns":
        pieces: list[tuple[float, float]] = []
        total = 0.0
        while total < distance_m + 1.0:
            straight = float(rng.uniform(35.0, 80.0))
            radius = float(rng.uniform(12.0, 22.0))
            sign = 1.0 if rng.random() < 0.5 else -1.0
            pieces += [(straight, 0.0), (0.5 * np.pi * radius, sign / radius)]
            total += straight + 0.5 * np.pi * radius
        return pieces
    if kind == "loop":
        # A rounded rectangle driven once and ~15 % more, so the start is revisited.
        radius = 14.0
        perimeter = max(distance_m / 1.15, 2.0 * np.pi * radius + 20.0)
        straights = perimeter - 2.0 * np.pi * radius
        a, b = 0.6 * straights / 2.0, 0.4 * straights / 2.0
        corner = (0.5 * np.pi * radius, -1.0 / radius)  # left turns: counter-clockwise from above
        lap = [(a / 2.0, 0.0), corner, (b, 0.0), corner, (a, 0.0), corner, (b, 0.0), corner,
               (a / 2.0, 0.0)]
        return lap + lap
    raise SynthError(f"unknown path kind {kind!r}; use one of {', '.join(PATH_KINDS)}")


def procedural(kind: str, frames: int, seed: int) -> np.ndarray:
    """A procedural drive of ``frames`` poses at 10 Hz: ``straight``, ``turns`` or ``loop``.

    Speed varies smoothly between about 6 and 11 m/s; the vehicle pitches and rolls by a few
    tenths of a degree. Returns ``T_world_cam0`` (frames, 4, 4), first pose = identity.
    """
    if frames < 1:
        raise SynthError(f"frames must be >= 1, got {frames}")
    rng = np.random.default_rng([seed, 3001])
    t = np.arange(frames) / FRAME_RATE_HZ
    phase = rng.uniform(0, 2 * np.pi, 3)
    speed = 8.5 + 1.5 * np.sin(0.21 * t + phase[0]) + 1.0 * np.sin(0.083 * t + phase[1])
    s_frame = np.concatenate([[0.0], np.cumsum(speed[:-1] / FRAME_RATE_HZ)])
    pieces = _segments(kind, float(s_frame[-1]), rng)

    ds = 0.05
    curv = np.concatenate([np.full(max(1, int(round(length / ds))), k) for length, k in pieces])
    heading = np.concatenate([[0.0], np.cumsum(curv * ds)])
    x = np.concatenate([[0.0], np.cumsum(np.sin(heading[:-1]) * ds)])
    z = np.concatenate([[0.0], np.cumsum(np.cos(heading[:-1]) * ds)])
    s_grid = np.arange(heading.size) * ds
    if s_frame[-1] > s_grid[-1]:
        raise SynthError("internal: procedural path shorter than the drive")

    yaw = np.interp(s_frame, s_grid, heading)
    px = np.interp(s_frame, s_grid, x)
    pz = np.interp(s_frame, s_grid, z)
    pitch = 0.004 * np.sin(1.3 * t + phase[2])
    roll = 0.003 * np.sin(0.9 * t + phase[0])
    T = np.zeros((frames, 4, 4))
    for i in range(frames):
        R = so3.exp([0.0, yaw[i], 0.0]) @ so3.exp([pitch[i], 0.0, 0.0]) @ so3.exp([0.0, 0.0, roll[i]])
        T[i] = se3.from_rt(R, [px[i], 0.0, pz[i]])
    return rebase(T)
