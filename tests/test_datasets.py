"""Dataset readers on small generated fixtures (every format) and on ../shared/data."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from dataset_fixtures import CX, CY, FX, B, H, W, gray, poses
from metricslam.datasets import (
    KittiOdometry,
    KittiRawDepth,
    Sequence,
    detect_format,
    open_sequence,
)
from metricslam.errors import CalibrationError, DatasetError, TrajectoryError
from metricslam.trajectory.io import write_kitti_poses


def kitti_calib_text(fx=FX, baseline=B) -> str:
    P0 = [fx, 0, CX, 0, 0, fx, CY, 0, 0, 0, 1, 0]
    P1 = list(P0)
    P1[3] = -fx * baseline
    fmt = lambda P: " ".join(f"{v:.12e}" for v in P)  # noqa: E731
    return f"P0: {fmt(P0)}\nP1: {fmt(P1)}\nP2: {fmt(P0)}\nP3: {fmt(P1)}\nTr: {fmt(P0)}\n"


def make_kitti(root: Path, n: int = 5, depth: bool = True, ext: str = ".png") -> Path:
    """root/sequences/00 with images (``ext``), calib, times, depth; poses at root/poses/00.txt."""
    seq = root / "sequences" / "00"
    for cam in ("image_0", "image_1"):
        (seq / cam).mkdir(parents=True)
        for i in range(n):
            cv2.imwrite(str(seq / cam / f"{i:06d}{ext}"), gray(i + (cam == "image_1")))
    if depth:
        (seq / "depth_0").mkdir()
        for i in range(n):
            d = np.zeros((H, W), np.uint16)
            d[5, 7] = 256 * (i + 1) + 128  # (i + 1.5) m
            cv2.imwrite(str(seq / "depth_0" / f"{i:06d}.png"), d)
    (seq / "calib.txt").write_text(kitti_calib_text())
    (seq / "times.txt").write_text("".join(f"0.{i}00000001\n" for i in range(n)))
    write_kitti_poses(root / "poses" / "00.txt", poses(n))
    return seq


# ---------------------------------------------------------------- KITTI odometry

def test_kitti_reads_everything(tmp_path):
    seq = make_kitti(tmp_path)
    s = KittiOdometry(seq)
    assert isinstance(s, Sequence) and s.name == "00" and len(s) == 5
    assert s.camera.fx_px == FX and (s.camera.width_px, s.camera.height_px) == (W, H)
    assert s.baseline_m == pytest.approx(B)
    assert s.t_ns.dtype == np.int64 and s.t_ns[0] == 1 and s.t_ns[3] == 300_000_001
    assert np.allclose(s.T_world_cam_gt, poses(5), atol=1e-8)
    f = s[2]
    assert f.index == 2 and f.image.dtype == np.uint8 and f.image.shape == (H, W)
    assert np.array_equal(f.image, gray(2)) and np.array_equal(f.image_right, gray(3))
    assert f.baseline_m == pytest.approx(B) and f.camera == s.camera
    assert f.depth_m.dtype == np.float32 and f.depth_m[5, 7] == pytest.approx(3.5)
    assert np.count_nonzero(f.depth_m) == 1
    assert s[-1].index == 4 and len(list(s)) == 5
    with pytest.raises(IndexError):
        s[5]


def test_kitti_reads_jpeg_frames_with_png_depth(tmp_path):
    """A KITTI-layout drive stored as JPEG (the residential_1405 drive of ../shared/data) loads like
    a PNG one; its depth maps stay uint16 PNG beside the JPEG frames."""
    seq = make_kitti(tmp_path, ext=".jpg")
    s = KittiOdometry(seq)
    assert len(s) == 5 and s.baseline_m == pytest.approx(B)
    assert [p.suffix for p in s.image_paths] == [".jpg"] * 5
    f = s[2]
    assert f.image.shape == (H, W) and f.image_right.shape == (H, W)
    assert np.abs(f.image.astype(int) - gray(2).astype(int)).mean() < 8  # lossy, but the same image
    assert f.depth_m[5, 7] == pytest.approx(3.5)


def test_kitti_optional_parts(tmp_path):
    seq = make_kitti(tmp_path, depth=False)
    (seq / "times.txt").unlink()
    s = KittiOdometry(seq, load_right=False)
    assert s.baseline_m is None and s[0].image_right is None and s[0].depth_m is None
    assert s.t_ns.tolist() == [0, 100_000_000, 200_000_000, 300_000_000, 400_000_000]


def test_kitti_pose_file_lookup_order(tmp_path):
    seq = make_kitti(tmp_path)
    local = poses(5, seed=9)
    write_kitti_poses(seq / "poses" / "mine.txt", local)
    assert np.allclose(KittiOdometry(seq).T_world_cam_gt, local, atol=1e-8)
    explicit = poses(5, seed=10)
    write_kitti_poses(tmp_path / "x.txt", explicit)
    assert np.allclose(KittiOdometry(seq, poses_file=tmp_path / "x.txt").T_world_cam_gt, explicit, atol=1e-8)
    write_kitti_poses(seq / "poses" / "other.txt", local)
    with pytest.raises(DatasetError, match="poses_file"):
        KittiOdometry(seq)


def test_kitti_without_ground_truth(tmp_path):
    seq = make_kitti(tmp_path)
    (tmp_path / "poses" / "00.txt").unlink()
    s = KittiOdometry(seq)
    assert s.T_world_cam_gt is None and s[0].T_world_cam is None


@pytest.mark.parametrize(
    "calib, line, match",
    [
        ("P0: 1 2 3\n", 1, "12 numbers"),
        ("# c\nP0: " + "1 " * 12 + "\nP1 1 2\n", 3, "KEY: numbers"),
        ("P1: " + "1 " * 12 + "\n", None, "P0"),
        ("P0: " + "x " * 12 + "\n", 1, "expected numbers"),
    ],
)
def test_kitti_malformed_calib(tmp_path, calib, line, match):
    seq = make_kitti(tmp_path)
    (seq / "calib.txt").write_text(calib)
    with pytest.raises(CalibrationError, match=match) as info:
        KittiOdometry(seq)
    assert info.value.line == line and info.value.path == str(seq / "calib.txt")


def test_kitti_calib_without_p1_but_stereo_images(tmp_path):
    seq = make_kitti(tmp_path)
    (seq / "calib.txt").write_text(kitti_calib_text().splitlines()[0] + "\n")
    with pytest.raises(CalibrationError, match="P1"):
        KittiOdometry(seq)
    assert KittiOdometry(seq, load_right=False).baseline_m is None


def test_kitti_count_mismatches_and_bad_times(tmp_path):
    seq = make_kitti(tmp_path)
    write_kitti_poses(tmp_path / "poses" / "00.txt", poses(4))
    with pytest.raises(TrajectoryError, match="4 poses"):
        KittiOdometry(seq)
    write_kitti_poses(tmp_path / "poses" / "00.txt", poses(5))
    (seq / "times.txt").write_text("0\n0.1\n")
    with pytest.raises(DatasetError, match="2 timestamps"):
        KittiOdometry(seq)
    (seq / "times.txt").write_text("0\n0.1\nabc\n0.3\n0.4\n")
    with pytest.raises(DatasetError, match="timestamp") as info:
        KittiOdometry(seq)
    assert info.value.line == 3
    (seq / "times.txt").write_text("0\n0.1\n0.1\n0.3\n0.4\n")
    with pytest.raises(DatasetError, match="increase") as info:
        KittiOdometry(seq)
    assert info.value.line == 3


def test_kitti_missing_parts_and_broken_images(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        KittiOdometry(tmp_path / "nope")
    seq = make_kitti(tmp_path)
    (seq / "image_1" / "000003.png").unlink()
    with pytest.raises(DatasetError, match="000003.png"):
        KittiOdometry(seq)
    assert len(KittiOdometry(seq, load_right=False)) == 5
    (seq / "image_0" / "000001.png").write_bytes(b"not a png")
    s = KittiOdometry(seq, load_right=False)  # lazy: opening does not read frame 1
    with pytest.raises(DatasetError, match="cannot read image") as info:
        s[1]
    assert info.value.path.endswith("000001.png")
    (seq / "calib.txt").unlink()
    with pytest.raises(CalibrationError, match="does not exist"):
        KittiOdometry(seq)


def test_kitti_rejects_images_of_another_size(tmp_path):
    seq = make_kitti(tmp_path)
    cv2.imwrite(str(seq / "image_0" / "000004.png"), np.zeros((H + 2, W), np.uint8))
    with pytest.raises(DatasetError, match="one size"):
        KittiOdometry(seq)[4]


# ---------------------------------------------------------------- KITTI raw + LiDAR depth

def make_raw_depth(root: Path, n: int = 4, calib: str = "K: 50 51 19.5 14.5\n") -> Path:
    (root / "image_02").mkdir(parents=True)
    (root / "depth_02").mkdir()
    for i in range(n):
        img = np.zeros((H, W, 3), np.uint8)
        img[..., 2] = 200  # red in BGR order on disk
        cv2.imwrite(str(root / "image_02" / f"{i:010d}.png"), img)
        if i != 1:
            d = np.zeros((H, W), np.uint16)
            d[3, 4] = 5120  # 20 m
            cv2.imwrite(str(root / "depth_02" / f"{i:010d}.png"), d)
    (root / "calib.txt").write_text("# test\n" + calib)
    return root


def test_kitti_raw_depth_reads_colour_and_depth(tmp_path):
    s = KittiRawDepth(make_raw_depth(tmp_path / "raw"))
    assert len(s) == 4 and s.baseline_m is None and s.T_world_cam_gt is None
    assert s.camera.fx_px == 50 and s.camera.fy_px == 51
    f = s[0]
    assert f.image.shape == (H, W, 3) and f.image[0, 0].tolist() == [200, 0, 0]  # RGB
    assert f.depth_m[3, 4] == pytest.approx(20.0) and f.depth_m.dtype == np.float32
    assert s[1].depth_m is None
    assert s.t_ns.tolist() == [0, 100_000_000, 200_000_000, 300_000_000]
    assert detect_format(tmp_path / "raw") == "kitti_raw_depth"


def test_kitti_raw_depth_p_rect_and_timestamps(tmp_path):
    root = make_raw_depth(tmp_path / "raw", calib="P_rect_02: 60 0 20 1 0 60 15 0 0 0 1 0\n")
    (root / "image_02" / "timestamps.txt").write_text(
        "".join(f"2011-09-26 13:02:25.{i * 100_000_000 + 5:09d}\n" for i in range(4)))
    s = KittiRawDepth(root)
    assert s.camera.fx_px == 60 and s.camera.cx_px == 20
    assert np.diff(s.t_ns).tolist() == [100_000_000] * 3 and s.t_ns[0] % 1_000_000_000 == 5


def test_kitti_raw_depth_errors(tmp_path):
    root = make_raw_depth(tmp_path / "raw", calib="K: 1 2 3\n")
    with pytest.raises(CalibrationError, match="fx fy cx cy") as info:
        KittiRawDepth(root)
    assert info.value.line == 2
    (root / "calib.txt").write_text("nothing: 1\n")
    with pytest.raises(CalibrationError, match="'K:'"):
        KittiRawDepth(root)
    (root / "calib.txt").write_text("K: 50 50 20 15\n")
    cv2.imwrite(str(root / "depth_02" / "0000000000.png"), np.zeros((H, W), np.uint8))
    with pytest.raises(DatasetError, match="uint16"):
        KittiRawDepth(root)[0]


# ---------------------------------------------------------------- detection

def test_open_sequence_detects_and_forwards_options(tmp_path):
    seq = make_kitti(tmp_path / "k")
    s = open_sequence(seq, load_right=False)
    assert isinstance(s, KittiOdometry) and s.baseline_m is None
    with pytest.raises(DatasetError, match="unknown dataset layout"):
        open_sequence(tmp_path)
    with pytest.raises(DatasetError, match="does not exist"):
        open_sequence(tmp_path / "missing")
    with pytest.raises(DatasetError, match="unknown format"):
        open_sequence(seq, format="bag")


# ---------------------------------------------------------------- real data

@pytest.mark.data
def test_real_kitti_odometry(shared_data):
    root = shared_data / "kitti_odometry" / "sequences"
    s06 = open_sequence(root / "06")
    assert len(s06) == 51 and s06.T_world_cam_gt.shape == (51, 4, 4)
    assert s06.baseline_m == pytest.approx(0.537, abs=1e-3)
    assert (s06.camera.width_px, s06.camera.height_px) == (1226, 370)
    assert s06.t_ns[1] == 104_498_900 and np.all(np.diff(s06.t_ns) > 0)
    f = s06[50]
    assert f.image.shape == (370, 1226) and f.image_right.shape == (370, 1226)
    path_m = np.sum(np.linalg.norm(np.diff(s06.T_world_cam_gt[:, :3, 3], axis=0), axis=1))
    assert path_m == pytest.approx(59.9, abs=0.1)
    s03 = open_sequence(root / "03")
    assert len(s03) == 5 and s03.camera.fx_px == pytest.approx(721.5377)


@pytest.mark.data
def test_real_kitti_raw_lidar(shared_data):
    s = open_sequence(shared_data / "kitti_raw_lidar")
    assert isinstance(s, KittiRawDepth) and len(s) == 78
    assert s.camera.fx_px == pytest.approx(721.5377) and s.camera.width_px == 1242
    f = s[10]
    assert f.image.shape == (375, 1242, 3) and f.depth_m.shape == (375, 1242)
    valid = f.depth_m[f.depth_m > 0]
    assert valid.size > 5000 and 1.0 < np.median(valid) < 80.0 and valid.max() < 256.0
