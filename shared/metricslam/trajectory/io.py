"""Read and write trajectory files in the KITTI and TUM formats.

* KITTI odometry: one pose per line, 12 numbers, the top 3x4 of ``T_world_cam`` row-major
  (what the KITTI devkit and ``evo_traj kitti`` read). No timestamps.
* TUM: ``timestamp tx ty tz qx qy qz qw`` per line, timestamp in seconds, quaternion in
  ``x y z w`` order, ``#`` starts a comment line (what ``evo_traj tum`` reads).

Poses are ``T_world_cam`` (N, 4, 4) float64, see ``docs/conventions.md``. Timestamps are
``t_ns`` (N,) int64 nanoseconds; TUM text timestamps are converted without going through a
float so nanosecond stamps survive a round trip exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from metricslam.errors import GeometryError, TrajectoryError
from metricslam.geometry import so3

#: tolerance on ``R·Rᵀ = I`` for rotations read from files (KITTI files carry ~7 digits).
ROTATION_TOL = 1e-4


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """Read a KITTI pose file into ``T_world_cam`` (N, 4, 4).

    Raises:
        TrajectoryError: missing file, a line without exactly 12 numbers, a non-rotation, or an
            empty file. The message names the file and the 1-based line.
    """
    path = Path(path)
    lines = _read_lines(path)
    poses = []
    for line_no, text in lines:
        fields = text.split()
        if len(fields) != 12:
            raise TrajectoryError(
                f"expected 12 numbers (a 3x4 row-major pose) per line, got {len(fields)}; "
                "is this a TUM file? use --format tum",
                path, line_no,
            )
        values = _floats(fields, path, line_no)
        T = np.eye(4)
        T[:3, :] = np.reshape(values, (3, 4))
        _check_pose(T, path, line_no)
        poses.append(T)
    if not poses:
        raise TrajectoryError("file holds no poses", path)
    return np.stack(poses)


def write_kitti_poses(path: str | Path, T_world_cam: np.ndarray) -> None:
    """Write poses (N, 4, 4) (or (N, 3, 4)) as a KITTI pose file (parent folders are created)."""
    T = _as_pose_array(T_world_cam)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as f:
        for pose in T:
            # Shortest repr that reads back to the same float64: exact round trips.
            f.write(" ".join(np.format_float_scientific(v, unique=True) for v in pose[:3, :].reshape(-1)) + "\n")


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory: ``(t_ns (N,) int64, T_world_cam (N, 4, 4))``.

    Raises:
        TrajectoryError: missing file, a line without exactly 8 numbers, a zero quaternion,
            timestamps that go backwards, or an empty file.
    """
    path = Path(path)
    stamps: list[int] = []
    poses = []
    for line_no, text in _read_lines(path):
        fields = text.replace(",", " ").split()
        if len(fields) != 8:
            raise TrajectoryError(
                f"expected 8 numbers 'timestamp tx ty tz qx qy qz qw' per line, got {len(fields)}; "
                "is this a KITTI file? use --format kitti",
                path, line_no,
            )
        t_ns = seconds_text_to_ns(fields[0], path, line_no)
        values = _floats(fields[1:], path, line_no)
        try:
            R = so3.from_quat_xyzw(values[3:7])
        except GeometryError as exc:
            raise TrajectoryError(f"bad quaternion qx qy qz qw: {exc}", path, line_no) from exc
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = values[:3]
        if stamps and t_ns <= stamps[-1]:
            raise TrajectoryError(
                f"timestamps must increase strictly, {fields[0]} follows {stamps[-1] / 1e9:.9f}",
                path, line_no,
            )
        stamps.append(t_ns)
        poses.append(T)
    if not poses:
        raise TrajectoryError("file holds no poses", path)
    return np.asarray(stamps, dtype=np.int64), np.stack(poses)


def write_tum(path: str | Path, t_ns: np.ndarray, T_world_cam: np.ndarray) -> None:
    """Write a TUM trajectory; ``t_ns`` (N,) int nanoseconds, ``T_world_cam`` (N, 4, 4)."""
    T = _as_pose_array(T_world_cam)
    stamps = np.asarray(t_ns).astype(np.int64).reshape(-1)
    if stamps.shape[0] != T.shape[0]:
        raise TrajectoryError(f"{stamps.shape[0]} timestamps for {T.shape[0]} poses", path)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, pose in zip(stamps, T):
            q = so3.to_quat_xyzw(so3.project_to_so3(pose[:3, :3]))
            x, y, z = pose[:3, 3]
            f.write(f"{ns_to_seconds_text(int(t))} {x:.9f} {y:.9f} {z:.9f} "
                    f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")


def read_trajectory(path: str | Path, fmt: str = "auto") -> tuple[np.ndarray | None, np.ndarray]:
    """Read a KITTI or TUM file: ``(t_ns or None, T_world_cam)``.

    ``fmt="auto"`` decides by the number of fields on the first data line (12 KITTI, 8 TUM).
    """
    if fmt == "auto":
        fmt = sniff_format(path)
    if fmt == "kitti":
        return None, read_kitti_poses(path)
    if fmt == "tum":
        return read_tum(path)
    raise TrajectoryError(f"unknown trajectory format {fmt!r}; use auto, kitti or tum", path)


def sniff_format(path: str | Path) -> str:
    """``"kitti"`` or ``"tum"`` from the field count of the first data line."""
    for line_no, text in _read_lines(Path(path)):
        n = len(text.replace(",", " ").split())
        if n == 12:
            return "kitti"
        if n == 8:
            return "tum"
        raise TrajectoryError(
            f"cannot tell the format: expected 12 numbers (KITTI) or 8 (TUM) per line, got {n}",
            path, line_no,
        )
    raise TrajectoryError("file holds no poses", path)


def seconds_text_to_ns(text: str, path: object = None, line: int | None = None) -> int:
    """Exact decimal seconds text (``"1403636579.763555527"``, ``"1.0e-01"``) -> int ns."""
    from decimal import Decimal, InvalidOperation

    try:
        value = Decimal(text)
    except InvalidOperation:
        raise TrajectoryError(f"expected a timestamp in seconds, got {text!r}", path, line) from None
    if not value.is_finite():
        raise TrajectoryError(f"timestamp {text!r} is not finite", path, line)
    return int((value * 1_000_000_000).to_integral_value())


def ns_to_seconds_text(t_ns: int) -> str:
    """int ns -> ``"S.NNNNNNNNN"`` (exact)."""
    sign = "-" if t_ns < 0 else ""
    sec, frac = divmod(abs(int(t_ns)), 1_000_000_000)
    return f"{sign}{sec}.{frac:09d}"


def _read_lines(path: Path) -> list[tuple[int, str]]:
    """Non-empty, non-comment lines with their 1-based numbers."""
    try:
        raw = path.read_text()
    except FileNotFoundError:
        raise TrajectoryError("trajectory file does not exist", path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TrajectoryError(f"cannot read trajectory file as text: {exc}", path) from None
    out = []
    for i, line in enumerate(raw.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            out.append((i, s))
    return out


def _floats(fields: list[str], path: Path, line_no: int) -> np.ndarray:
    try:
        values = np.array([float(v) for v in fields])
    except ValueError:
        raise TrajectoryError(f"expected numbers, got {' '.join(fields)!r}", path, line_no) from None
    if not np.all(np.isfinite(values)):
        raise TrajectoryError("pose contains NaN or inf", path, line_no)
    return values


def _check_pose(T: np.ndarray, path: Path, line_no: int) -> None:
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > ROTATION_TOL or np.linalg.det(R) < 0:
        raise TrajectoryError(
            "the 3x3 block is not a rotation (R·Rᵀ != I or det < 0); expected a rigid pose",
            path, line_no,
        )


def _as_pose_array(T_world_cam: np.ndarray) -> np.ndarray:
    T = np.asarray(T_world_cam, dtype=float)
    if T.ndim != 3 or T.shape[1:] not in ((4, 4), (3, 4)):
        raise TrajectoryError(f"expected poses of shape (N, 4, 4) or (N, 3, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise TrajectoryError("poses contain NaN or inf; refusing to write them")
    return T
