"""``metricslam synth`` rig options (focal length, baseline, mounting height): known answers.

The defaults must stay KITTI's rig (the renders of ``tests/test_synth.py`` stay byte-identical);
another rig must reach ``calib.txt`` and the readers, its road must lie where fx and the height
put it, its stereo pair must be offset by ``fx·B/z``, and its chessboard photos must calibrate
back to its intrinsics.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from metricslam.calibration import make_calibration
from metricslam.chessboard import calibrate_chessboard
from metricslam.datasets import open_sequence
from metricslam.datasets.kitti import read_kitti_calib
from metricslam.synth import SynthConfig, SynthScene, generate_sequence, kitti_like_camera
from metricslam.synth.board import INNER_CORNERS, SQUARE_M, board_photos
from metricslam.synth.photometric import PhotometricConfig
from metricslam.synth.world import WorldConfig
from metricslam_cli import synth_cmd
from metricslam_cli.main import main as cli_main

REPO = Path(__file__).resolve().parents[1]
FX_PX, BASELINE_M, HEIGHT_M = 150.0, 0.12, 0.7
SIZE = (320, 180)


def _rig_config(width: int, height: int, clean: bool = True) -> SynthConfig:
    photo = (PhotometricConfig(noise_sigma=0.0, vignetting=0.0, exposure_log_sigma=0.0) if clean
             else PhotometricConfig())
    return SynthConfig(width_px=width, height_px=height, fx_px=FX_PX, baseline_m=BASELINE_M,
                       world=WorldConfig(camera_height_m=HEIGHT_M), photometric=photo)


def _cli_args(*extra: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    synth_cmd.add_parser(parser.add_subparsers())
    return parser.parse_args(["synth", "out", "--frames", "1", *extra])


def test_cli_defaults_are_the_kitti_rig() -> None:
    """No rig option = ``SynthConfig()``: KITTI's focal length, 0.54 m, 1.65 m (same bytes)."""
    assert synth_cmd.synth_config(_cli_args()) == SynthConfig()
    assert kitti_like_camera(620, 188, None) == kitti_like_camera(620, 188)
    cfg = synth_cmd.synth_config(_cli_args("--fx", "424", "--baseline-m", "0.12", "--height-m", "0.7"))
    assert (cfg.fx_px, cfg.baseline_m, cfg.world.camera_height_m) == (424.0, 0.12, 0.7)


def test_rig_reaches_calib_txt_and_the_reader(tmp_path: Path) -> None:
    out = tmp_path / "rig"
    generate_sequence(out, frames=2, seed=3, size=SIZE, path="straight", config=_rig_config(*SIZE, False))
    calib = read_kitti_calib(out / "calib.txt")
    assert calib["P0"][0, 0] == FX_PX and calib["P0"][1, 1] == FX_PX
    assert -calib["P1"][0, 3] / calib["P1"][0, 0] == pytest.approx(BASELINE_M, rel=1e-14)
    seq = open_sequence(out)
    assert seq.camera.fx_px == FX_PX and (seq.camera.width_px, seq.camera.height_px) == SIZE
    assert seq.baseline_m == pytest.approx(BASELINE_M, rel=1e-14)


def test_road_lies_where_fx_and_the_height_put_it() -> None:
    """Level camera HEIGHT_M above a flat road: the road at row v has depth fy·h/(v − cy)."""
    T_path = np.tile(np.eye(4), (40, 1, 1))
    T_path[:, 2, 3] = np.arange(40.0)
    scene = SynthScene(T_path, seed=4, config=_rig_config(*SIZE))
    cam = scene.camera
    assert cam.fx_px == FX_PX and cam.fy_px == FX_PX
    depth, tri_id, _ = scene.renderer.visibility(T_path[3])
    u = int(round(cam.cx_px))
    rows = np.arange(int(np.ceil(cam.cy_px)) + 8, cam.height_px)
    z = depth[rows, u]
    expected = cam.fy_px * HEIGHT_M / (rows - cam.cy_px)
    # the ribbon sinks 10 µm per metre of arc (test_synth.py): far below the 1e-3 tolerance
    np.testing.assert_allclose(z, expected, rtol=1e-3)
    # the KITTI height would put the same rows 1.65/0.7 times further away: the option matters
    assert np.all(np.abs(z / (expected * 1.65 / HEIGHT_M) - 1) > 0.5)


def _photometric_error(left: np.ndarray, right: np.ndarray, depth: np.ndarray, fx_px: float,
                       baseline_m: float, shift_px: float) -> float:
    """Median |left − right(u − fx·B/z − shift)| on textured pixels without depth edges."""
    h, w = left.shape
    gx = cv2.Sobel(left.astype(np.float32), cv2.CV_32F, 1, 0, ksize=3)
    dmax = cv2.dilate(depth, np.ones((7, 7), np.uint8))
    dmin = cv2.erode(depth, np.ones((7, 7), np.uint8))
    disparity = np.where(depth > 0, fx_px * baseline_m / np.maximum(depth, 1e-6), 0.0)
    map_x = (np.arange(w)[None, :] - disparity - shift_px).astype(np.float32)
    mask = (np.abs(gx) > 40) & (dmin > 0) & (dmax - dmin < 0.05 * dmin) & (map_x >= 0)
    map_y = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, axis=1)
    warped = cv2.remap(right.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR)
    assert mask.sum() > 1500, "too few textured pixels to test"
    return float(np.median(np.abs(warped - left.astype(np.float32))[mask]))


def test_stereo_pair_is_offset_by_fx_b_over_z() -> None:
    """The rendered right image is the left one shifted by fx·B/z of the depth map: the
    photometric error is smallest at exactly that disparity, for this rig's fx and B."""
    scene = SynthScene.procedural(12, seed=2, path="turns", config=_rig_config(480, 270))
    f = scene.frame(6)
    fx = scene.camera.fx_px
    exact = _photometric_error(f.left, f.right, f.depth_m, fx, BASELINE_M, 0.0)
    assert exact < 2.5
    for shift in (-0.5, 0.5):
        assert _photometric_error(f.left, f.right, f.depth_m, fx, BASELINE_M, shift) > 1.5 * exact
    # KITTI's baseline would be the wrong answer by far
    assert _photometric_error(f.left, f.right, f.depth_m, fx, 0.54, 0.0) > 3 * exact


def test_board_photos_calibrate_back_to_the_rig_camera() -> None:
    cam = kitti_like_camera(848, 480, 424.0)
    photos = board_photos(cam, 12, seed=0)
    result = calibrate_chessboard([(f"{i}", p) for i, p in enumerate(photos)], INNER_CORNERS, SQUARE_M)
    assert len(result.used) >= 10 and result.rms_px < 0.3
    np.testing.assert_allclose(result.calibration.camera.K, cam.K, rtol=0.005, atol=1.5)


def test_cli_refuses_bad_rig_options(tmp_path: Path) -> None:
    for bad in (["--fx", "-3"], ["--baseline-m", "0"], ["--height-m", "0.1"], ["--board-photos", "-1"]):
        assert cli_main(["synth", str(tmp_path / "x"), "--frames", "1", "--size", "64x32",
                         "--no-progress", *bad]) == 1


def test_the_calib_txt_snippet_in_own_camera_md_writes_what_the_readers_read(tmp_path: Path) -> None:
    """docs/own_camera.md's write_calib_txt.py: a --calib YAML and a baseline -> calib.txt with
    that fx, cx, cy and baseline, for the trainer and KittiOdometry alike."""
    page = (REPO / "docs" / "own_camera.md").read_text()
    blocks = [b.split("```", 1)[0] for b in page.split("```python\n")[1:]]
    snippet = next(b for b in blocks if b.startswith("# write_calib_txt.py"))
    (tmp_path / "write_calib_txt.py").write_text(snippet)
    K = np.array([[423.7, 0.0, 415.2], [0.0, 423.9, 236.6], [0.0, 0.0, 1.0]])
    (tmp_path / "cam.yaml").write_text(make_calibration(K, 848, 480).to_yaml())
    seq = tmp_path / "drive"
    seq.mkdir()
    r = subprocess.run([sys.executable, str(tmp_path / "write_calib_txt.py"), str(tmp_path / "cam.yaml"),
                        "0.12", str(seq)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    calib = read_kitti_calib(seq / "calib.txt")
    np.testing.assert_array_equal(calib["P0"][:, :3], K)
    assert (calib["P0"][0, 3] - calib["P1"][0, 3]) / calib["P1"][0, 0] == pytest.approx(0.12, rel=1e-14)
