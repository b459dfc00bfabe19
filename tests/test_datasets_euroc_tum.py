"""Dataset readers on generated fixtures: EuRoC and TUM RGB-D (KITTI ones: test_datasets.py)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from dataset_fixtures import CX, CY, FX, H, W, gray, poses
from metricslam.calibration import make_calibration
from metricslam.camera import PinholeCamera
from metricslam.datasets import EuRoC, TumRgbd, detect_format
from metricslam.errors import CalibrationError, DatasetError, TrajectoryError
from metricslam.geometry import se3, so3
from metricslam.trajectory.io import write_tum

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
    f = s[0]  # Freiburg 1 images are undistorted with the published coefficients (same K)
    assert f.image.shape == (H, W, 3) and f.image[H // 2, W // 2, 0] == 1
    assert f.depth_m[H // 2, W // 2] == pytest.approx(2.0)  # depth 15 ms earlier, within 20 ms
    assert s.undistort_maps is not None
    assert detect_format(root) == "tum"
    assert len(TumRgbd(root, require_groundtruth=False)) == 6


def test_tum_explicit_camera_and_errors(tmp_path):

    root = make_tum(tmp_path / "seq")
    cam = PinholeCamera(fx_px=10, fy_px=10, cx_px=20, cy_px=15, width_px=W, height_px=H)
    assert TumRgbd(root, camera=cam).camera == cam
    with pytest.raises(CalibrationError, match="--calib"):  # no intrinsics, no Freiburg name: no guess
        TumRgbd(root)
    calib = make_calibration(cam.K, W, H, "radtan", (0.1, 0.0, 0.0, 0.0), source="test")
    s = TumRgbd(root, calibration=calib)
    assert s.camera == cam and s.undistort_maps is not None
    (root / "rgb.txt").write_text("# x\n1305031102.1 rgb/a.png extra\n")
    with pytest.raises(DatasetError, match="timestamp filename") as info:
        TumRgbd(root, camera=cam)
    assert info.value.line == 2
    (root / "rgb.txt").write_text("1305031102.1 rgb/a.png\n")
    (root / "groundtruth.txt").write_text("1 2 3\n")
    with pytest.raises(TrajectoryError, match="8 numbers"):
        TumRgbd(root, camera=cam)
