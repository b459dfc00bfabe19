"""FrameReader (issue #21): reads only what an estimator uses and decodes one frame ahead on a
reader thread, without changing a single pixel or the order unreadable frames are reported in."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
from dataset_fixtures import CX, CY, FX, H, W, gray
from metricslam.datasets import KittiOdometry
from metricslam.datasets.frame_reader import FrameReader


def _stereo_kitti_with_depth(root: Path, n: int) -> Path:
    for sub in ("image_0", "image_1", "depth_0"):
        (root / sub).mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), gray(i))
        cv2.imwrite(str(root / "image_1" / f"{i:06d}.png"), gray(i + 7))
        cv2.imwrite(str(root / "depth_0" / f"{i:06d}.png"), np.full((H, W), 256 * (i + 1), np.uint16))
    P0 = " ".join(f"{v:.6e}" for v in (FX, 0, CX, 0, 0, FX, CY, 0, 0, 0, 1, 0))
    P1 = " ".join(f"{v:.6e}" for v in (FX, 0, CX, -FX * 0.5, 0, FX, CY, 0, 0, 0, 1, 0))
    (root / "calib.txt").write_text(f"P0: {P0}\nP1: {P1}\n")
    (root / "times.txt").write_text("".join(f"{i / 10:.6f}\n" for i in range(n)))
    return root


def test_reader_gives_the_left_image_only_and_exactly(tmp_path):
    seq = KittiOdometry(_stereo_kitti_with_depth(tmp_path / "seq", 5))
    assert seq[0].image_right is not None and seq[0].depth_m is not None  # the sequence has both
    with FrameReader(seq) as reader:
        for i in range(len(seq)):
            frame, full = reader[i], seq[i]
            assert frame.index == i and frame.t_ns == full.t_ns and frame.camera == full.camera
            assert np.array_equal(frame.image, full.image)
            assert frame.image_right is None and frame.depth_m is None and frame.baseline_m is None


def test_read_ahead_matches_plain_reads_in_any_access_order(tmp_path):
    seq = KittiOdometry(_stereo_kitti_with_depth(tmp_path / "seq", 6))
    order = [0, 1, 2, 4, 3, 5, 5, 0, -1]
    with FrameReader(seq) as ahead:
        got = [ahead[i] for i in order]
    plain = FrameReader(seq, read_ahead=False)
    for i, frame in zip(order, got):
        ref = plain[i]
        assert frame.index == ref.index and np.array_equal(frame.image, ref.image)


def test_unreadable_frames_are_reported_when_asked_for_not_when_read_ahead(tmp_path):
    seq_dir = _stereo_kitti_with_depth(tmp_path / "seq", 5)
    seq = KittiOdometry(seq_dir)
    (seq_dir / "image_0" / "000002.png").write_bytes(b"not a png")
    (seq_dir / "image_0" / "000004.png").unlink()
    reader = FrameReader(seq)
    frames = [reader[i] for i in range(3)]  # frame 3 is being read ahead, 4 not yet
    assert reader.unreadable == [2]
    assert frames[2].image.shape == (H, W) and not frames[2].image.any()  # black = invalid frame
    frames += [reader[3], reader[4]]
    assert reader.unreadable == [2, 4]
    assert [f.index for f in frames] == list(range(5))
    reader.close()


def test_close_ends_the_reader_thread(tmp_path):
    seq = KittiOdometry(_stereo_kitti_with_depth(tmp_path / "seq", 3))
    before = set(threading.enumerate())
    reader = FrameReader(seq)
    reader[0]
    mine = [t for t in threading.enumerate() if t not in before and t.name.startswith("frame-reader")]
    assert mine
    reader.close()
    assert not any(t.is_alive() for t in mine)
    assert reader[1].index == 1  # still readable, now without read-ahead
