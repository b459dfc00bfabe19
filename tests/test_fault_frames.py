"""Issue #19: bad input frames never abort a run and never leave stale poses in the trajectory.

* an unreadable image (garbage, truncated, missing, wrong size) becomes one invalid frame, is
  logged and counted (``frames_unreadable``), and ``metricslam run`` still writes every pose;
* a frame without a pose of its own (invalid input, tracking loss) is interpolated between its
  neighbours in one world frame, or marked ``pose_valid=False`` — never the VO's stale pose
  (KITTI 06 with frames 20-24 black used to put frames 20-25 ~16 m behind their neighbours).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from dataset_fixtures import CX, CY, FX, H, W
from metricslam.datasets import KittiOdometry
from metricslam.datasets.frame_reader import FrameReader
from metricslam.geometry import se3, so3
from metricslam.slam.pose_gaps import fill_pose_gaps
from metricslam.slam.types import PoseEstimate, TrackingState
from metricslam.slam.vo.frame_check import usable_gray
from metricslam.trajectory.io import read_kitti_poses, read_tum
from metricslam_cli.main import main as cli_main

PERIOD_NS = 100_000_000


# ---------------------------------------------------------------- unreadable frames

def _tiny_kitti(root: Path, n: int) -> Path:
    (root / "image_0").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):  # textured: the VO's blank-frame check must not reject them
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), rng.integers(0, 256, (H, W), np.uint8))
    P0 = " ".join(f"{v:.6e}" for v in (FX, 0, CX, 0, 0, FX, CY, 0, 0, 0, 1, 0))
    (root / "calib.txt").write_text(f"P0: {P0}\n")
    (root / "times.txt").write_text("".join(f"{i / 10:.6f}\n" for i in range(n)))
    return root


def test_every_kind_of_unreadable_image_becomes_one_logged_invalid_frame(tmp_path, caplog):
    seq_dir = _tiny_kitti(tmp_path / "seq", 6)
    images = seq_dir / "image_0"
    png = (images / "000002.png").read_bytes()
    seq = KittiOdometry(seq_dir)  # lazy: the files below break after opening
    (images / "000001.png").write_bytes(np.random.default_rng(0).bytes(3000))  # garbage
    (images / "000002.png").write_bytes(png[: len(png) // 2])  # truncated
    (images / "000003.png").unlink()  # missing
    cv2.imwrite(str(images / "000004.png"), np.zeros((H + 2, W), np.uint8))  # wrong size
    reader = FrameReader(seq)
    with caplog.at_level(logging.WARNING, logger="metricslam.datasets.frame_reader"):
        frames = [reader[i] for i in range(len(reader))]
    assert reader.unreadable == [1, 2, 3, 4]
    for i, frame in enumerate(frames):
        assert frame.index == i and frame.t_ns == int(seq.t_ns[i])
        assert frame.image.shape == (H, W)
        # the VO's invalid-frame path: unusable images are not tracked
        assert (usable_gray(frame.image, seq.camera, 2.0) is None) == (i in reader.unreadable)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 4  # one per bad frame, naming its index and file
    for i, text in zip((1, 2, 3, 4), warnings):
        assert f"frame {i} " in text and f"{i:06d}.png" in text


@pytest.fixture()
def kitti06(shared_data) -> Path:
    seq = shared_data / "kitti_odometry" / "sequences" / "06"
    if not (seq / "image_0").is_dir():
        pytest.skip(f"KITTI odometry sequence 06 is absent from {shared_data}")
    return seq


def _copy_sequence(src: Path, dst: Path, n: int | None = None) -> Path:
    """KITTI folder with the first ``n`` left images of ``src`` (symlinks), calib and times."""
    names = sorted(p.name for p in (src / "image_0").glob("*.png"))[:n]
    (dst / "image_0").mkdir(parents=True)
    for name in names:
        os.symlink((src / "image_0" / name).resolve(), dst / "image_0" / name)
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    times = (src / "times.txt").read_text().splitlines()[: len(names)]
    (dst / "times.txt").write_text("\n".join(times) + "\n")
    return dst


def _replace(path: Path, data: bytes) -> None:
    path.unlink()
    path.write_bytes(data)


def _run(seq_dir: Path, out: Path, *extra: str) -> dict:
    stats = out.with_suffix(".json")
    rc = cli_main(["run", str(seq_dir), "--out", str(out), "--json", str(stats), "--deterministic",
                   "--no-progress", *extra])
    assert rc == 0
    return json.loads(stats.read_text())


def _chord_distance_m(p: np.ndarray, a: int, b: int, k: int) -> float:
    d = p[b] - p[a]
    t = np.clip(np.dot(p[k] - p[a], d) / max(np.dot(d, d), 1e-12), 0.0, 1.0)
    return float(np.linalg.norm(p[k] - (p[a] + t * d)))


def test_run_survives_a_corrupt_and_a_truncated_png(kitti06, tmp_path):
    seq_dir = _copy_sequence(kitti06, tmp_path / "06_20", 20)
    png = (seq_dir / "image_0" / "000012.png").read_bytes()
    _replace(seq_dir / "image_0" / "000007.png", np.random.default_rng(1).bytes(5000))
    _replace(seq_dir / "image_0" / "000012.png", png[: len(png) // 4])
    out = tmp_path / "est.txt"
    stats = _run(seq_dir, out)
    T = read_kitti_poses(out)
    assert T.shape == (20, 4, 4) and np.all(np.isfinite(T))
    assert stats["frames_unreadable"] == 2 and stats["unreadable_frame_indices"] == [7, 12]
    assert stats["invalid_frames"] >= 2 and stats["pose_invalid"] == 0
    assert {7, 12} <= set(stats["interpolated_frame_indices"])
    p = T[:, :3, 3]
    for k in (7, 12):
        assert _chord_distance_m(p, k - 1, k + 1, k) < 0.5


def test_blacked_out_frames_get_interpolated_not_stale_poses(kitti06, tmp_path):
    """Frames 20-24 black (frame 25 then loses tracking) and 47-50 black (no frame after)."""
    seq_dir = _copy_sequence(kitti06, tmp_path / "06_black")
    black = np.zeros_like(cv2.imread(str(seq_dir / "image_0" / "000000.png"), cv2.IMREAD_GRAYSCALE))
    for k in [*range(20, 25), *range(47, 51)]:
        (seq_dir / "image_0" / f"{k:06d}.png").unlink()
        cv2.imwrite(str(seq_dir / "image_0" / f"{k:06d}.png"), black)
    out = tmp_path / "est.txt"
    stats = _run(seq_dir, out)
    T = read_kitti_poses(out)
    assert T.shape == (51, 4, 4)
    interp = stats["interpolated_frame_indices"]
    assert set(range(20, 25)) <= set(interp) and stats["interpolated"] == len(interp)
    # nothing after 46 has a pose: placeholders, listed, repeating frame 46's pose in KITTI files
    assert stats["pose_invalid_frame_indices"] == [47, 48, 49, 50]
    assert np.allclose(T[47:, :3, 3], T[46, :3, 3])
    p = T[:, :3, 3]
    after = min(k for k in range(25, 47) if k not in interp)
    worst = max(_chord_distance_m(p, 19, after, k) for k in range(20, after))
    assert worst < 0.5, f"interpolated frames {worst:.2f} m off the chord of their neighbours"
    # TUM files have timestamps: frames without a pose are left out
    tum = tmp_path / "est.tum"
    _run(seq_dir, tum, "--format", "tum")
    t_ns, T_tum = read_tum(tum)
    assert len(t_ns) == 47 and np.allclose(T_tum[:, :3, 3], p[:47], atol=1e-6)


# ---------------------------------------------------------------- gap filling (pure)

def _est(k: int, T: np.ndarray, segment: int = 0, t_ns: int | None = None) -> PoseEstimate:
    return PoseEstimate(k, k * PERIOD_NS if t_ns is None else t_ns, T, TrackingState.TRACKING,
                        segment_id=segment)


def _pose(yaw_rad: float, x_m: float) -> np.ndarray:
    return se3.from_rt(so3.exp(np.array([0.0, yaw_rad, 0.0])), np.array([x_m, 0.0, 0.0]))


def test_gaps_are_interpolated_in_time_and_on_the_rotation_geodesic():
    stale = _pose(2.0, -16.0)  # what the VO left in a frame it could not track
    # uneven stamps: frame 3 (250 ms) is a quarter of the way from frame 2 (200) to frame 4 (400)
    T = [_pose(0.0, 0.0), _pose(0.1, 1.0), _pose(0.2, 2.0), stale, _pose(0.6, 6.0)]
    poses = [_est(k, T[k], t_ns=t_ms * 1_000_000) for k, t_ms in enumerate((0, 100, 200, 250, 400))]
    out = fill_pose_gaps(poses, [True, True, True, False, True], [False] * 5)
    assert [e.interpolated for e in out] == [False, False, False, True, False]
    assert all(e.pose_valid for e in out)
    assert np.allclose(out[3].T_world_cam, _pose(0.3, 3.0))  # alpha = (250-200)/(400-200)
    for k in (0, 1, 2, 4):
        assert out[k] is poses[k]  # frames with a pose of their own are untouched
    everyone = [True] * 5
    assert fill_pose_gaps(poses, everyone, everyone) is poses


@pytest.mark.parametrize("linked", [True, False])
def test_gaps_across_a_segment_change_need_a_common_world(linked):
    """Frames 3 (invalid, segment 0) and 4 (lost, segment 1) between 2 (segment 0) and 5
    (segment 1): interpolated when both sides come from the global graph (which links the
    segments), else placeholders from their own segment's side, marked invalid."""
    poses = [_est(k, _pose(0.0, float(k)), segment=0 if k < 4 else 1) for k in range(7)]
    poses[3] = _est(3, _pose(0.0, -16.0), segment=0)
    poses[4] = _est(4, _pose(0.0, -16.0), segment=1)
    own = [True, True, True, False, False, True, True]
    out = fill_pose_gaps(poses, own, [linked] * 7)
    if linked:
        assert [e.interpolated for e in out[3:5]] == [True, True] and all(e.pose_valid for e in out)
        assert np.allclose([e.T_world_cam[0, 3] for e in out], range(7))
    else:
        assert [e.pose_valid for e in out] == own and not any(e.interpolated for e in out)
        assert out[3].T_world_cam[0, 3] == 2.0 and out[4].T_world_cam[0, 3] == 5.0
    # segment 1 relocalized in the session's map and its link dropped: both sides come from the
    # graph, but how the camera got from one to the other is unknown, so nothing is interpolated
    relinked = fill_pose_gaps(poses, own, [True] * 7, relinked={1})
    assert [e.pose_valid for e in relinked] == own and not any(e.interpolated for e in relinked)


def test_gaps_at_either_end_have_no_pose():
    """Before the first pose the VO sits at its world origin (where the first keyframe will be);
    after the last one, the frame repeats the last pose instead of the VO's stale one."""
    poses = [_est(k, np.eye(4) if k < 2 else _pose(0.0, float(k) if k < 4 else -16.0)) for k in range(6)]
    out = fill_pose_gaps(poses, [False, False, True, True, False, False], [True] * 6)
    assert [e.pose_valid for e in out] == [False, False, True, True, False, False]
    assert not any(e.interpolated for e in out)
    assert [e.T_world_cam[0, 3] for e in out] == [0.0, 0.0, 2.0, 3.0, 3.0, 3.0]
    nothing = fill_pose_gaps(poses[:2], [False, False], [False, False])  # no pose anywhere yet
    assert not any(e.pose_valid for e in nothing)
