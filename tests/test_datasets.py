"""Dataset readers on small generated fixtures (every format) and on ../shared/data."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from metricslam.datasets import (
    EuRoC,
    KittiOdometry,
    KittiRawDepth,
    Sequence,
    TumRgbd,
    detect_format,
    open_sequence,
)
from metricslam.errors import CalibrationError, DatasetError, TrajectoryError
from metricslam.geometry import se3, so3
from metricslam.trajectory.io import write_kitti_poses, write_tum

W, H = 40, 30
FX, CX, CY, B = 50.0, 19.5, 14.5, 0.5


def gray(i: int) -> np.ndarray:
    img = np.full((H, W), 10 * i % 256, np.uint8)
    img[i % H, :] = 255
    return img


def poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([se3.exp(np.concatenate([rng.normal(0, 0.1, 3), [0, 0, float(i)]]))
                     for i in range(n)])


def kitti_calib_text(fx=FX, baseline=B) -> str:
    P0 = [fx, 0, CX, 0, 0, fx, CY, 0, 0, 0, 1, 0]
    P1 = list(P0)
    P1[3] = -fx * baseline
    fmt = lambda P: " ".join(f"{v:.12e}" for v in P)  # noqa: E731
    return f"P0: {fmt(P0)}\nP1: {fmt(P1)}\nP2: {fmt(P0)}\nP3: {fmt(P1)}\nTr: {fmt(P0)}\n"


def make_kitti(root: Path, n: int = 5, depth: bool = True) -> Path:
    """root/sequences/00 with images, calib, times, depth; poses at root/poses/00.txt."""
    seq = root / "sequences" / "00"
    for cam in ("image_0", "image_1"):
        (seq / cam).mkdir(parents=True)
        for i in range(n):
            cv2.imwrite(str(seq / cam / f"{i:06d}.png"), gray(i + (cam == "image_1")))
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


# ---------------------------------------------------------------- EuRoC

T_BS = se3.from_rt(so3.exp(np.array([0.0, 0.0, np.pi / 2])), np.array([-0.02, -0.06, 0.01]))
T0_NS = 1_403_636_579_763_555_584


def body_pose(t_ns: np.ndarray) -> np.ndarray:
    """Constant velocity and constant yaw rate: interpolation is exact in position and slerp."""
    tau = (np.asarray(t_ns) - T0_NS) / 1e9
    T = np.tile(np.eye(4), (len(tau), 1, 1))
    T[:, :3, 3] = np.column_stack([tau, 2 * tau, 0.5 + 0 * tau])
    T[:, :3, :3] = [so3.exp(np.array([0.0, 0.0, 0.3 * x])) for x in tau]
    return T


def make_euroc(root: Path, n: int = 6, dist=(0.0, 0.0, 0.0, 0.0)) -> Path:
    cam = root / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    stamps = T0_NS + np.arange(n, dtype=np.int64) * 50_000_000
    lines = ["#timestamp [ns],filename"]
    for i, t in enumerate(stamps):
        cv2.imwrite(str(cam / "data" / f"{t}.png"), gray(i))
        lines.append(f"{t},{t}.png")
    (cam / "data.csv").write_text("\n".join(lines) + "\n")
    data = ", ".join(f"{v:.15g}" for v in T_BS.reshape(-1))
    (cam / "sensor.yaml").write_text(
        "%YAML:1.0\n# General sensor definitions.\nsensor_type: camera\n"
        f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\n"
        f"rate_hz: 20\nresolution: [{W}, {H}]\ncamera_model: pinhole\n"
        f"intrinsics: [{FX}, {FX + 1}, {CX}, {CY}] #fu, fv, cu, cv\n"
        f"distortion_model: radial-tangential\ndistortion_coefficients: {list(dist)}\n")
    # ground truth at 200 Hz, starting after the first image and ending before the last
    t_gt = np.arange(stamps[0] + 20_000_000, stamps[-1] - 20_000_000, 5_000_000, dtype=np.int64)
    gt = body_pose(t_gt)
    rows = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"]
    for t, T in zip(t_gt, gt):
        x, y, z, w = so3.to_quat_xyzw(T[:3, :3])
        rows.append(f"{t},{T[0, 3]:.9f},{T[1, 3]:.9f},{T[2, 3]:.9f},{w:.12f},{x:.12f},{y:.12f},{z:.12f}"
                    ",0,0,0,0,0,0,0,0,0")
    gtdir = root / "mav0" / "state_groundtruth_estimate0"
    gtdir.mkdir()
    (gtdir / "data.csv").write_text("\n".join(rows) + "\n")
    return root


def test_euroc_reads_intrinsics_extrinsics_and_camera_ground_truth(tmp_path):
    s = EuRoC(make_euroc(tmp_path / "MH_01_easy"))
    assert s.name == "MH_01_easy"
    assert (s.camera.fx_px, s.camera.fy_px, s.camera.width_px) == (FX, FX + 1, W)
    assert np.allclose(s.T_body_cam, T_BS)
    # frames 0 and 5 lie outside the ground-truth span and are dropped
    assert len(s) == 4 and s.t_ns[0] == T0_NS + 50_000_000
    assert np.allclose(s.T_world_cam_gt, body_pose(s.t_ns) @ T_BS, atol=1e-7)
    f = s[0]
    assert np.array_equal(f.image, gray(1)) and f.T_world_cam is not None
    assert detect_format(tmp_path / "MH_01_easy") == "euroc"
    assert len(EuRoC(tmp_path / "MH_01_easy" / "mav0", trim_to_groundtruth=False)) == 6


def test_euroc_undistorts_images(tmp_path):
    root = make_euroc(tmp_path / "V1", dist=(-0.3, 0.1, 0.0, 0.0))
    raw = EuRoC(root, undistort=False)[0].image
    und = EuRoC(root)[0].image
    assert und.shape == raw.shape and not np.array_equal(und, raw)


def test_euroc_malformed_files(tmp_path):
    root = make_euroc(tmp_path / "V1")
    yaml_path = root / "mav0" / "cam0" / "sensor.yaml"
    good = yaml_path.read_text()
    yaml_path.write_text(good.replace("intrinsics: [", "intrinsics: [1, "))
    with pytest.raises(CalibrationError, match="intrinsics"):
        EuRoC(root)
    yaml_path.write_text(good.replace("camera_model: pinhole", "camera_model: omni"))
    with pytest.raises(CalibrationError, match="omni"):
        EuRoC(root)
    yaml_path.write_text(good)
    gt = root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = gt.read_text().splitlines()
    lines[3] = lines[3].replace(",", ";", 2)
    gt.write_text("\n".join(lines) + "\n")
    with pytest.raises(TrajectoryError) as info:
        EuRoC(root)
    assert info.value.line == 4
    csv = root / "mav0" / "cam0" / "data.csv"
    csv.write_text("#timestamp [ns],filename\n123;x.png\n")
    with pytest.raises(DatasetError, match="timestamp_ns,filename") as info:
        EuRoC(root)
    assert info.value.line == 2


# ---------------------------------------------------------------- TUM RGB-D

def make_tum(root: Path, n: int = 6) -> Path:
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    t_rgb = [f"1305031102.{175304 + 33333 * i:06d}" for i in range(n)]
    t_depth = [f"1305031102.{160407 + 33333 * i:06d}" for i in range(n)]  # 15 ms before rgb
    rgb_lines = ["# color images", "# file: 'x.bag'", "# timestamp filename"]
    depth_lines = ["# depth maps"]
    for i in range(n):
        cv2.imwrite(str(root / "rgb" / f"{t_rgb[i]}.png"), np.full((H, W, 3), i, np.uint8))
        rgb_lines.append(f"{t_rgb[i]} rgb/{t_rgb[i]}.png")
        d = np.full((H, W), 5000 * (i + 1), np.uint16)
        cv2.imwrite(str(root / "depth" / f"{t_depth[i]}.png"), d)
        depth_lines.append(f"{t_depth[i]} depth/{t_depth[i]}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    # ground truth at 100 Hz starting after the first image (which is then dropped)
    t_gt = np.arange(1305031102_200000000, 1305031102_500000000, 10_000_000, dtype=np.int64)
    write_tum(root / "groundtruth.txt", t_gt, poses(len(t_gt), seed=3))
    return root


def test_tum_association_depth_and_presets(tmp_path):
    root = make_tum(tmp_path / "rgbd_dataset_freiburg1_xyz")
    s = TumRgbd(root)
    assert (s.camera.fx_px, s.camera.cx_px) == (517.3 * W / 640, (318.6 + 0.5) * W / 640 - 0.5)
    assert len(s) == 5 and s.t_ns[0] == 1305031102_208637000
    # the first image is 24.7 ms before the first pose (dropped); then the nearest pose
    t_gt = np.arange(1305031102_200000000, 1305031102_500000000, 10_000_000, dtype=np.int64)
    gt = poses(len(t_gt), seed=3)
    idx = [int(np.argmin(np.abs(t_gt - t))) for t in s.t_ns]
    assert np.allclose(s.T_world_cam_gt, gt[idx], atol=1e-7)
    f = s[0]
    assert f.image.shape == (H, W, 3) and f.image[0, 0, 0] == 1
    assert f.depth_m[0, 0] == pytest.approx(2.0)  # depth 15 ms earlier, within 20 ms
    assert detect_format(root) == "tum"
    assert len(TumRgbd(root, require_groundtruth=False)) == 6


def test_tum_explicit_camera_and_errors(tmp_path):
    from metricslam.camera import PinholeCamera

    root = make_tum(tmp_path / "seq")
    cam = PinholeCamera(fx_px=10, fy_px=10, cx_px=20, cy_px=15, width_px=W, height_px=H)
    assert TumRgbd(root, camera=cam).camera == cam
    assert TumRgbd(root).camera.fx_px == pytest.approx(525.0 * W / 640)
    (root / "rgb.txt").write_text("# x\n1305031102.1 rgb/a.png extra\n")
    with pytest.raises(DatasetError, match="timestamp filename") as info:
        TumRgbd(root)
    assert info.value.line == 2
    (root / "rgb.txt").write_text("1305031102.1 rgb/a.png\n")
    (root / "groundtruth.txt").write_text("1 2 3\n")
    with pytest.raises(TrajectoryError, match="8 numbers"):
        TumRgbd(root)


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
