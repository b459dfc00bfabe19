"""Synthetic stereo worlds: geometry agrees with the images, seeds reproduce, KITTI layout reads."""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from metricslam.datasets.kitti import KittiOdometry, read_kitti_calib
from metricslam.errors import SynthError, TrajectoryError
from metricslam.geometry import so3
from metricslam.synth import SynthConfig, SynthScene, generate_sequence, kitti_like_camera
from metricslam.synth import materials as mt
from metricslam.synth import trajectory as trj
from metricslam.synth import world as world_mod
from metricslam.synth.photometric import PhotometricConfig
from metricslam.trajectory.io import read_kitti_poses, write_kitti_poses
from metricslam_cli.main import main as cli_main

SMALL = (320, 96)


def _clean_config(width: int, height: int) -> SynthConfig:
    """No noise, vignetting or exposure change: left and right see the same radiance."""
    photo = PhotometricConfig(noise_sigma=0.0, vignetting=0.0, exposure_log_sigma=0.0)
    return SynthConfig(width_px=width, height_px=height, photometric=photo)


@pytest.fixture(scope="module")
def small_seq(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "seq"
    generate_sequence(out, frames=4, seed=5, size=SMALL, path="turns")
    return out


@pytest.fixture(scope="module")
def clean_scene() -> SynthScene:
    return SynthScene.procedural(40, seed=2, path="turns", config=_clean_config(620, 188))


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_calib_is_exact(small_seq: Path) -> None:
    calib = read_kitti_calib(small_seq / "calib.txt")
    cam = kitti_like_camera(*SMALL)
    np.testing.assert_array_equal(calib["P0"][:, :3], cam.K)
    np.testing.assert_array_equal(calib["P2"], calib["P0"])
    np.testing.assert_array_equal(calib["P3"], calib["P1"])
    assert calib["P0"][0, 3] == 0.0
    assert calib["P1"][0, 3] == pytest.approx(-cam.fx_px * 0.54, rel=1e-13)
    np.testing.assert_array_equal(np.delete(calib["P1"], 3, axis=1), calib["P0"][:, :3])


def test_kitti_reader_reads_output(small_seq: Path) -> None:
    seq = KittiOdometry(small_seq)
    assert len(seq) == 4
    assert seq.baseline_m == pytest.approx(0.54, abs=1e-12)
    assert (seq.camera.width_px, seq.camera.height_px) == SMALL
    np.testing.assert_allclose(np.diff(seq.t_ns), 100_000_000)
    T = seq.T_world_cam_gt
    np.testing.assert_allclose(T[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(T, trj.procedural("turns", 4, 5), atol=1e-11)
    frame = seq[2]
    assert frame.image.shape == (SMALL[1], SMALL[0]) and frame.image.dtype == np.uint8
    assert frame.image_right is not None and frame.image_right.shape == frame.image.shape
    raw = cv2.imread(str(small_seq / "depth_0" / "000002.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    np.testing.assert_allclose(frame.depth_m, raw / 256.0, atol=1e-6)
    assert (frame.depth_m > 0).mean() > 0.4  # the street fills most of the view


def test_seed_reproduces_byte_identically(small_seq: Path, tmp_path: Path) -> None:
    generate_sequence(tmp_path / "again", frames=4, seed=5, size=SMALL, path="turns")
    assert _digest(tmp_path / "again") == _digest(small_seq)
    generate_sequence(tmp_path / "other", frames=4, seed=6, size=SMALL, path="turns")
    other = _digest(tmp_path / "other")
    assert other["image_0/000000.png"] != _digest(small_seq)["image_0/000000.png"]


def test_refuses_to_overwrite(small_seq: Path) -> None:
    with pytest.raises(SynthError, match="not empty"):
        generate_sequence(small_seq, frames=1, seed=5, size=SMALL)


def _textured_mask(img: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Pixels with image gradient and a locally planar-ish depth (no occlusion edges)."""
    gx = cv2.Sobel(img.astype(np.float32), cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img.astype(np.float32), cv2.CV_32F, 0, 1, ksize=3)
    grad = np.hypot(gx, gy)
    dmax = cv2.dilate(depth, np.ones((7, 7), np.uint8))
    dmin = cv2.erode(depth, np.ones((7, 7), np.uint8))
    smooth = (dmin > 0) & (dmax - dmin < 0.05 * dmin)
    return (grad > 40) & smooth


def _reprojection_errors(left: np.ndarray, right: np.ndarray, depth: np.ndarray,
                         depth_right: np.ndarray, fx_px: float, baseline_m: float,
                         extra_shift_px: float = 0.0) -> np.ndarray:
    h, w = left.shape
    mask = _textured_mask(left, depth)
    disparity = np.where(depth > 0, fx_px * baseline_m / np.maximum(depth, 1e-6), 0.0)
    map_x = (np.arange(w)[None, :] - disparity - extra_shift_px).astype(np.float32)
    map_y = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, axis=1)
    warped = cv2.remap(right.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=-1000.0)
    mask &= (map_x >= 0) & (map_x <= w - 1)
    # the right camera must also see the point (not occluded): its depth there agrees
    seen = cv2.remap(depth_right, map_x, map_y, cv2.INTER_NEAREST)
    mask &= np.abs(seen - depth) < 0.03 * depth
    return np.abs(warped - left.astype(np.float32))[mask]


def test_left_depth_reprojects_into_right_at_fx_b_over_d(clean_scene: SynthScene) -> None:
    cam = clean_scene.camera
    for index in (0, 17, 33):
        f = clean_scene.frame(index)
        _, depth_right = clean_scene.renderer.render(f.T_world_cam @ clean_scene.T_cam0_cam1)
        err = _reprojection_errors(f.left, f.right, f.depth_m, depth_right, cam.fx_px, 0.54)
        assert err.size > 2000, "too few textured pixels to test"
        assert np.median(err) < 2.5
        # the photometric error is smallest at exactly fx·B/d: shifting the disparity by a
        # fraction of a pixel either way makes it worse (so the check can fail)
        shifts = (-1.0, -0.5, -0.25, 0.25, 0.5, 1.0)
        shifted = [np.median(_reprojection_errors(f.left, f.right, f.depth_m, depth_right,
                                                  cam.fx_px, 0.54, extra_shift_px=s))
                   for s in shifts]
        assert min(shifted) > np.median(err)
        assert shifted[0] > 2 * np.median(err) and shifted[-1] > 2 * np.median(err)


def test_right_depth_matches_left_depth_at_the_disparity(clean_scene: SynthScene) -> None:
    """Rectified rig: a point has the same z in both cameras, so depth warps consistently."""
    T = clean_scene.T_world_cam[10]
    cam = clean_scene.camera
    _, depth_l = clean_scene.renderer.render(T)
    _, depth_r = clean_scene.renderer.render(T @ clean_scene.T_cam0_cam1)
    v, u = np.nonzero(depth_l > 0)
    d = depth_l[v, u]
    ur = u - cam.fx_px * 0.54 / d
    ok = (ur >= 0) & (ur <= cam.width_px - 1)
    nearest = depth_r[v[ok], np.rint(ur[ok]).astype(int)]
    rel = np.abs(nearest - d[ok]) / d[ok]
    # occluded pixels and the half-pixel rounding at slanted surfaces disagree; most agree
    assert np.mean(rel < 0.02) > 0.93


def test_depth_is_metric_on_the_road() -> None:
    """Road pixels unprojected with their depth land on the road plane 1.65 m below the path."""
    T_path = np.tile(np.eye(4), (30, 1, 1))
    T_path[:, 2, 3] = np.arange(30.0)  # level drive along z: the road is the plane y = 1.65
    scene = SynthScene(T_path, seed=4, config=_clean_config(320, 96))
    T = T_path[5].copy()
    T[:3, :3] = so3.exp([0.02, 0.3, -0.01])  # look around: depth must not depend on it
    depth, tri_id, _ = scene.renderer.visibility(T)
    road = (tri_id >= 0)
    road[road] = scene.world.mesh.material[tri_id[road]] == mt.ROAD
    v, u = np.nonzero(road)
    assert v.size > 1000
    p_cam = scene.camera.unproject(np.stack([u, v], 1).astype(float), depth[v, u])
    p_world = p_cam @ T[:3, :3].T + T[:3, 3]
    # the ribbon sinks 10 µm per metre of path (arc length counted from margin_before_m
    # behind the start) so that crossings resolve without z-fighting
    arc_m = p_world[:, 2] + scene.config.world.margin_before_m
    np.testing.assert_allclose(p_world[:, 1], 1.65 + world_mod._SINK_PER_M * arc_m, atol=1e-6)


def test_motion_blur_blurs_images_not_depth() -> None:
    blur = PhotometricConfig(noise_sigma=0.0, vignetting=0.0, motion_blur_samples=4)
    sharp = SynthScene.procedural(5, seed=3, path="straight", config=_clean_config(160, 48))
    blurred = SynthScene.procedural(5, seed=3, path="straight",
                                    config=SynthConfig(width_px=160, height_px=48, photometric=blur))
    a, b = sharp.frame(2), blurred.frame(2)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    assert np.abs(a.left.astype(int) - b.left.astype(int)).mean() > 0.5
    # blur averages neighbouring views: less high-frequency energy than the sharp image
    lap = [np.abs(cv2.Laplacian(f.left, cv2.CV_32F)).mean() for f in (a, b)]
    assert lap[1] < lap[0]


def test_procedural_paths() -> None:
    for kind in trj.PATH_KINDS:
        T = trj.procedural(kind, 300, seed=1)
        assert T.shape == (300, 4, 4)
        np.testing.assert_allclose(T[0], np.eye(4), atol=1e-12)
        step = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
        assert 0.4 < step.min() and step.max() < 1.3  # 4..13 m/s at 10 Hz
        for R in T[:, :3, :3]:
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    loop = trj.procedural("loop", 300, seed=1)
    gap = np.linalg.norm(loop[:, :3, 3] - loop[0, :3, 3], axis=1)
    assert gap[100:].min() < 3.0, "the loop must come back to its start"
    with pytest.raises(SynthError):
        trj.procedural("zigzag", 10, seed=0)


def test_kitti_pose_file_errors(tmp_path: Path) -> None:
    bad = tmp_path / "bad.txt"
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 2 3\n")
    with pytest.raises(TrajectoryError, match=":2"):
        read_kitti_poses(bad)
    with pytest.raises(SynthError, match="--start"):
        trj.kitti_segment(_write_poses(tmp_path), 5, start=3)


def _write_poses(tmp_path: Path) -> Path:
    path = tmp_path / "ok.txt"
    write_kitti_poses(path, trj.procedural("straight", 6, seed=0))
    return path


@pytest.mark.data
def test_world_along_kitti_00_has_content(shared_data: Path) -> None:
    poses = shared_data / "kitti_gt_poses_full" / "00.txt"
    T = trj.kitti_segment(poses, 400, start=3000)
    scene = SynthScene(T, seed=0, config=_clean_config(310, 94))
    for index in range(0, 400, 40):
        _, depth = scene.renderer.render(T[index])
        assert (depth > 0).mean() > 0.5
        h, w = depth.shape
        centre = depth[h // 2 - 3:h // 2 + 3, w // 2 - 3:w // 2 + 3]
        assert not ((centre > 0) & (centre < 3.0)).any(), f"something blocks the road at frame {index}"


def test_cli_writes_sequence(tmp_path: Path) -> None:
    out = tmp_path / "cli"
    assert cli_main(["synth", str(out), "--frames", "2", "--seed", "1", "--size", "160x48",
                     "--path", "straight", "--no-progress"]) == 0
    assert sorted(p.name for p in (out / "image_1").iterdir()) == ["000000.png", "000001.png"]
    assert cli_main(["synth", str(out), "--frames", "2", "--no-progress"]) == 1  # not empty
    assert cli_main(["synth", str(tmp_path / "tiny"), "--frames", "2", "--size", "12x5",
                     "--no-progress"]) == 1
    assert cli_main(["synth", str(tmp_path / "none"), "--frames", "2", "--trajectory",
                     str(tmp_path / "missing.txt"), "--no-progress"]) == 1
