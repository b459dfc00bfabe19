"""Calibration files (metricslam, OpenCV FileStorage, EuRoC sensor.yaml), undistortion with the
same K, chessboard calibration on rendered photos, and the commands that refuse to guess."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from metricslam.calibration import Calibration, load_calibration, make_calibration
from metricslam.camera import PinholeCamera
from metricslam.chessboard import board_points, calibrate_chessboard
from metricslam.errors import CalibrationError
from metricslam.geometry import so3

CLI = [sys.executable, "-m", "metricslam_cli.main"]
W, H = 640, 480
K = np.array([[500.0, 0, 322.5], [0, 505.0, 236.0], [0, 0, 1]])
RADTAN = (-0.21, 0.06, 0.001, -0.0008, 0.0)


def test_the_three_formats_load_to_one_calibration(tmp_path: Path) -> None:
    ours = make_calibration(K, W, H, "radtan", RADTAN[:4], source="x")
    (tmp_path / "ours.yaml").write_text(ours.to_yaml())
    fs = cv2.FileStorage(str(tmp_path / "opencv.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", W)
    fs.write("image_height", H)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.array(RADTAN[:4]).reshape(4, 1))
    fs.write("avg_reprojection_error", 0.21)
    fs.release()
    (tmp_path / "sensor.yaml").write_text(
        "%YAML:1.0\ncamera_model: pinhole\nintrinsics: [500.0, 505.0, 322.5, 236.0]\n"
        f"resolution: [{W}, {H}]\ndistortion_model: radial-tangential\n"
        f"distortion_coefficients: {list(RADTAN[:4])}\n")
    loaded = [load_calibration(tmp_path / n) for n in ("ours.yaml", "opencv.yaml", "sensor.yaml")]
    for c in loaded:
        assert c.camera == ours.camera and c.distortion_model == "radtan"
        assert np.allclose(c.distortion_coefficients, RADTAN[:4])


@pytest.mark.parametrize("text, needle", [
    ("fx: 500\nfy: 500\ncx: 1\ncy: 1\nwidth: 64\n", "'height'"),
    ("fx: 500\nfy: 500\ncx: 1\ncy: 1\nwidth: 64\nheight: 48\nk1: 0.1\n", "unknown key"),
    ("fx: -5\nfy: 500\ncx: 1\ncy: 1\nwidth: 64\nheight: 48\n", "focal"),
    ("fx: 500\nfy: 500\ncx: 1\ncy: 1\nwidth: 64\nheight: 48\ndistortion_model: radtan\n"
     "distortion_coefficients: [0.1, 0.2]\n", "takes 4 or 5"),
    ("fx: 500\nfy: 500\ncx: 1\ncy: 1\nwidth: 64\nheight: 48\ndistortion_model: omni\n", "omni"),
    ("focal: 500\n", "unknown calibration format"),
    ("fx: [1\n", "not valid YAML"),
])
def test_bad_files_say_what_is_wrong(tmp_path: Path, text: str, needle: str) -> None:
    path = tmp_path / "cam.yaml"
    path.write_text(text)
    with pytest.raises(CalibrationError, match=needle) as info:
        load_calibration(path)
    assert str(path) in str(info.value)


def test_rescaled_for_the_same_aspect_refused_for_another() -> None:
    c = make_calibration(K, W, H)
    half = c.for_image(320, 240)
    assert half.camera.fx_px == pytest.approx(250.0)
    with pytest.raises(CalibrationError, match="aspect ratio"):
        c.for_image(640, 360)
    assert make_calibration(K, W, H, "radtan", (0, 0, 0, 0)).undistort_maps() is None


def render_board(R: np.ndarray, t: np.ndarray, square_m: float = 0.025) -> np.ndarray:
    """A 10x7-square board (9x6 inner corners) seen by the pinhole camera K at pose (R, t)
    (board frame -> camera), gray background."""
    s_px, margin = 40, 40
    tex = np.full((7 * s_px + 2 * margin, 10 * s_px + 2 * margin), 255, np.uint8)
    for r in range(7):
        for c in range(10):
            if (r + c) % 2 == 0:
                tex[margin + r * s_px:margin + (r + 1) * s_px, margin + c * s_px:margin + (c + 1) * s_px] = 0
    q = square_m / s_px
    o = margin + s_px - 0.5  # texture coordinate of inner corner (0, 0)
    A = np.array([[q, 0, -o * q], [0, q, -o * q], [0, 0, 1]])
    Hm = K @ np.column_stack([R[:, 0], R[:, 1], t]) @ A
    return cv2.warpPerspective(tex, Hm, (W, H), flags=cv2.INTER_AREA, borderValue=128)


def distort(img: np.ndarray, coeffs) -> np.ndarray:
    """What a lens with radtan ``coeffs`` and matrix K makes of the pinhole image ``img``."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, K, np.array(coeffs), P=K).reshape(H, W, 2)
    return cv2.remap(img, und[..., 0], und[..., 1], cv2.INTER_LINEAR, borderValue=128)


@pytest.fixture(scope="module")
def board_photos() -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, distorted photo, pinhole photo) of 12 varied board poses."""
    rng = np.random.default_rng(7)
    out = []
    for i in range(12):
        R = so3.exp(np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)]))
        centre = board_points((9, 6), 0.025).mean(axis=0)
        t = np.array([rng.uniform(-0.08, 0.08), rng.uniform(-0.06, 0.06), rng.uniform(0.42, 0.6)]) - R @ centre
        pinhole = render_board(R, t)
        out.append((f"view{i:02d}.png", distort(pinhole, RADTAN), pinhole))
    return out


def test_chessboard_calibration_recovers_the_rendering_camera(board_photos) -> None:
    result = calibrate_chessboard([(n, d) for n, d, _ in board_photos], (9, 6), 0.025)
    c = result.calibration
    assert len(result.used) >= 10 and result.rms_px < 0.5
    assert np.allclose(c.camera.K, K, rtol=0.01, atol=1.5), c.camera
    assert c.distortion_coefficients[0] == pytest.approx(RADTAN[0], abs=0.03)
    with pytest.raises(CalibrationError, match="inner corners"):
        calibrate_chessboard([(n, d) for n, d, _ in board_photos[:5]], (8, 6), 0.025)


def test_undistortion_keeps_k_and_undoes_the_lens(board_photos) -> None:
    from metricslam.chessboard import find_corners

    maps = make_calibration(K, W, H, "radtan", RADTAN).undistort_maps()
    for _, distorted, pinhole in board_photos[:3]:
        truth = find_corners(pinhole, (9, 6)).reshape(-1, 2)
        seen = find_corners(distorted, (9, 6)).reshape(-1, 2)
        undone = find_corners(cv2.remap(distorted, *maps, cv2.INTER_LINEAR), (9, 6)).reshape(-1, 2)
        assert np.abs(seen - truth).max() > 1.0  # the lens moves corners by pixels
        assert np.abs(undone - truth).max() < 0.3  # undistorted to the same K: back in place


def test_calibrate_command_writes_a_file_run_and_camera_read(board_photos, tmp_path: Path) -> None:
    for name, distorted, _ in board_photos:
        cv2.imwrite(str(tmp_path / name), distorted)
    out = tmp_path / "cam.yaml"
    r = subprocess.run(CLI + ["calibrate", str(tmp_path), "--pattern", "9x6", "--square-mm", "25",
                              "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "RMS reprojection error" in r.stdout
    assert isinstance(load_calibration(out), Calibration)


def test_camera_refuses_to_start_without_intrinsics(tmp_path: Path) -> None:
    r = subprocess.run(CLI + ["camera", "--device", str(tmp_path / "none.avi")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "no camera intrinsics" in r.stderr and "--calib" in r.stderr
    r = subprocess.run(CLI + ["camera", "--device", "x.avi", "--fx", "500", "--assume-fov", "60"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "pass one" in r.stderr


def test_camera_intrinsics_from_each_source(tmp_path: Path, caplog) -> None:
    import argparse

    from metricslam_cli.camera_cmd import frame_calibration

    def args(**kw):
        base = dict(calib=None, assume_fov=None, fx=None, fy=None, cx=None, cy=None)
        return argparse.Namespace(**(base | kw))

    with caplog.at_level(logging.WARNING):
        guess = frame_calibration(args(assume_fov=90.0), 640, 480)
    assert guess.camera.fx_px == pytest.approx(320.0) and "NO CALIBRATION" in caplog.text
    assert frame_calibration(args(fx=600.0), 640, 480).camera.fx_px == 600.0
    (tmp_path / "c.yaml").write_text(make_calibration(K, W, H, "radtan", RADTAN).to_yaml())
    c = frame_calibration(args(calib=str(tmp_path / "c.yaml")), 320, 240)
    assert c.camera.fx_px == pytest.approx(250.0) and c.undistort_maps() is not None


def test_tum_published_calibration_by_name_warns(tmp_path: Path, caplog) -> None:
    from metricslam.datasets.tum import published_calibration, tum_calibration

    fr2 = published_calibration("rgbd_dataset_freiburg2_desk")
    assert fr2.camera == PinholeCamera(fx_px=520.9, fy_px=521.0, cx_px=325.1, cy_px=249.7,
                                       width_px=640, height_px=480)
    assert fr2.distortion_coefficients == (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)
    assert not published_calibration("fr3_office").has_distortion
    with caplog.at_level(logging.WARNING):
        tum_calibration(tmp_path / "rgbd_dataset_freiburg1_xyz")
    assert "NO CALIBRATION GIVEN" in caplog.text and "--calib" in caplog.text
    with pytest.raises(CalibrationError, match="--calib"):
        tum_calibration(tmp_path / "my_recording")


def test_the_opencv_snippet_in_the_docs_writes_a_file_calib_reads(board_photos, tmp_path: Path,
                                                                   repo_root: Path) -> None:
    page = (repo_root / "docs" / "calibration.md").read_text()
    snippet = page.split("```python\n", 1)[1].split("```", 1)[0]
    (tmp_path / "calibrate.py").write_text(snippet)
    photos = tmp_path / "photos"
    photos.mkdir()
    for name, distorted, _ in board_photos:
        cv2.imwrite(str(photos / name), distorted)
    out = tmp_path / "opencv.yaml"
    r = subprocess.run([sys.executable, str(tmp_path / "calibrate.py"), str(photos), "9", "6", "25", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    c = load_calibration(out)
    assert np.allclose(c.camera.K, K, rtol=0.01, atol=1.5) and c.distortion_model == "radtan"
