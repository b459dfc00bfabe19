"""KITTI and TUM trajectory files: round trips, interoperability with evo, typed errors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from metricslam.errors import TrajectoryError
from metricslam.geometry import se3
from metricslam.trajectory import io as tio

#: per-test settings (no global profile: other modules keep their own)
SETTINGS = settings(max_examples=40, deadline=None)


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([se3.exp(rng.normal(size=6) * [1, 1, 1, 20, 20, 20]) for _ in range(n)])


def test_kitti_round_trip(tmp_path):
    T = random_poses(25)
    path = tmp_path / "sub" / "est.txt"
    tio.write_kitti_poses(path, T)
    lines = path.read_text().splitlines()
    assert len(lines) == 25 and all(len(line.split()) == 12 for line in lines)
    assert np.allclose(tio.read_kitti_poses(path), T, atol=1e-8)
    assert tio.sniff_format(path) == "kitti"


def test_kitti_accepts_3x4_input(tmp_path):
    T = random_poses(3)
    tio.write_kitti_poses(tmp_path / "a.txt", T[:, :3, :])
    assert np.allclose(tio.read_kitti_poses(tmp_path / "a.txt"), T, atol=1e-8)


@SETTINGS
@given(st.lists(st.integers(0, 2**62), min_size=1, max_size=30, unique=True))
def test_tum_timestamps_round_trip_to_the_nanosecond(stamps):
    import tempfile
    from pathlib import Path

    t_ns = np.sort(np.asarray(stamps, dtype=np.int64))
    T = random_poses(len(t_ns), seed=len(t_ns))
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "t.txt"
        tio.write_tum(path, t_ns, T)
        t_back, T_back = tio.read_tum(path)
    assert t_back.dtype == np.int64 and np.array_equal(t_back, t_ns)
    assert np.allclose(T_back, T, atol=1e-7)


def test_tum_reads_xyzw_quaternions(tmp_path):
    # 90° about z, w last on disk
    path = tmp_path / "gt.txt"
    path.write_text("# comment\n1.5 1 2 3 0 0 0.7071067811865476 0.7071067811865476\n")
    t_ns, T = tio.read_tum(path)
    assert t_ns.tolist() == [1_500_000_000]
    assert np.allclose(T[0, :3, 3], [1, 2, 3])
    assert np.allclose(T[0, :3, :3] @ [1, 0, 0], [0, 1, 0])


def test_seconds_text_is_exact():
    assert tio.seconds_text_to_ns("1403636579.763555527") == 1403636579763555527
    assert tio.seconds_text_to_ns("1.0e-01") == 100_000_000
    assert tio.ns_to_seconds_text(1403636579763555527) == "1403636579.763555527"
    assert tio.ns_to_seconds_text(-1) == "-0.000000001"
    assert tio.seconds_text_to_ns(tio.ns_to_seconds_text(-1)) == -1


def test_evo_reads_our_files(tmp_path):
    from evo.tools import file_interface

    T = random_poses(10)
    t_ns = np.arange(10, dtype=np.int64) * 50_000_000 + 1_000_000_000_000
    tio.write_kitti_poses(tmp_path / "k.txt", T)
    tio.write_tum(tmp_path / "t.txt", t_ns, T)
    k = file_interface.read_kitti_poses_file(str(tmp_path / "k.txt"))
    t = file_interface.read_tum_trajectory_file(str(tmp_path / "t.txt"))
    assert np.allclose(np.stack(k.poses_se3), T, atol=1e-8)
    assert np.allclose(np.stack(t.poses_se3), T, atol=1e-7)
    assert np.allclose(t.timestamps, t_ns / 1e9)


def test_we_read_evo_files(tmp_path):
    from evo.core.trajectory import PosePath3D, PoseTrajectory3D
    from evo.tools import file_interface

    T = random_poses(8)
    stamps = 1e9 + np.arange(8) * 0.1
    file_interface.write_kitti_poses_file(str(tmp_path / "k.txt"), PosePath3D(poses_se3=list(T)))
    file_interface.write_tum_trajectory_file(
        str(tmp_path / "t.txt"), PoseTrajectory3D(poses_se3=list(T), timestamps=stamps))
    assert np.allclose(tio.read_kitti_poses(tmp_path / "k.txt"), T, atol=1e-6)
    t_ns, T_tum = tio.read_tum(tmp_path / "t.txt")
    assert np.allclose(T_tum, T, atol=1e-6)
    assert np.allclose(t_ns / 1e9, stamps, atol=1e-6)


@pytest.mark.parametrize(
    "text, line, match",
    [
        ("1 0 0 0 0 1 0 0 0 0 1\n", 1, "12 numbers"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 x 0 0 1 0\n", 2, "expected numbers"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n\n2 0 0 0 0 1 0 0 0 0 1 0\n", 3, "not a rotation"),
        ("1 0 0 0 0 1 0 0 0 0 1 nan\n", 1, "NaN"),
    ],
)
def test_malformed_kitti_file_names_file_and_line(tmp_path, text, line, match):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(TrajectoryError, match=match) as info:
        tio.read_kitti_poses(path)
    assert info.value.line == line and info.value.path == str(path)
    assert f"bad.txt:{line}:" in str(info.value)


@pytest.mark.parametrize(
    "text, line, match",
    [
        ("0.0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 0\n", 2, "8 numbers"),
        ("0.0 1 2 3 0 0 0 0\n", 1, "quaternion"),
        ("0.2 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 0 1\n", 2, "increase"),
        ("abc 1 2 3 0 0 0 1\n", 1, "timestamp"),
    ],
)
def test_malformed_tum_file_names_file_and_line(tmp_path, text, line, match):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(TrajectoryError, match=match) as info:
        tio.read_tum(path)
    assert info.value.line == line


def test_missing_empty_and_unknown_files(tmp_path):
    with pytest.raises(TrajectoryError, match="does not exist"):
        tio.read_kitti_poses(tmp_path / "nope.txt")
    (tmp_path / "empty.txt").write_text("# nothing\n\n")
    with pytest.raises(TrajectoryError, match="no poses"):
        tio.read_tum(tmp_path / "empty.txt")
    (tmp_path / "five.txt").write_text("1 2 3 4 5\n")
    with pytest.raises(TrajectoryError, match="12 numbers .KITTI. or 8 .TUM."):
        tio.read_trajectory(tmp_path / "five.txt")


def test_writers_refuse_nan_and_bad_shapes(tmp_path):
    T = random_poses(2)
    T[1, 0, 3] = np.nan
    with pytest.raises(TrajectoryError):
        tio.write_kitti_poses(tmp_path / "x.txt", T)
    with pytest.raises(TrajectoryError):
        tio.write_kitti_poses(tmp_path / "x.txt", np.eye(4))
    with pytest.raises(TrajectoryError):
        tio.write_tum(tmp_path / "x.txt", np.arange(3), random_poses(2))
