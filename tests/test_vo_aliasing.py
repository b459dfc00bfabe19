"""Aliased VO tracks on repeating texture (``metricslam.slam.vo.aliasing``): the re-track from the
global image shift (``docs/history/rule_vo_retrack2_session21.md``) and the suspect-frame report
(``docs/history/rule_vo_aliasing_report_session21.md``).

Where a turn starts or ends on a street of window grids, most KLT tracks can converge one window
period away, all agreeing, and the VO's shape goes wrong for several frames without a tracking
loss. A frame whose essential check rejects more than ``VOConfig.retrack_reject_share`` of its
tracks is tracked again from the global image shift (kept if that halves the share); frames still
above ``VOConfig.suspect_reject_share``, two in a row, are reported (``--json``, a warning line,
``PoseEstimate.vo_suspect``) — the report itself changes no estimate.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from metricslam.camera import PinholeCamera
from metricslam.geometry.align import align_trajectory
from metricslam.slam.vo.aliasing import SuspectFrames, describe_ranges
from metricslam.slam.vo.config import VOConfig
from metricslam.slam.vo.frontend import KLTFrontend
from metricslam.trajectory.io import read_kitti_poses
from metricslam_cli.main import main


H_PX, W_PX = 188, 620
PERIOD_PX, SHIFT_PX = 32, 12


def _facade_pair() -> tuple[np.ndarray, np.ndarray]:
    """Two (H, W) uint8 views of a wall of windows (horizontal period ``PERIOD_PX``) over a faint
    large-scale shading; in the second, the content has moved ``SHIFT_PX`` to the right."""
    rng = np.random.default_rng(0)
    w = W_PX + 64
    x, y = np.arange(w)[None, :], np.arange(H_PX)[:, None]
    windows = (((x % PERIOD_PX) < PERIOD_PX // 2) & ((y % 30) < 18)).astype(np.float32) * 90
    shading = cv2.GaussianBlur(rng.standard_normal((H_PX, w)).astype(np.float32), (0, 0), 25)
    wall = np.clip(windows + 15 * shading / shading.std() + 80 + rng.normal(0, 2, (H_PX, w)), 0, 255)
    wall = wall.astype(np.uint8)
    return wall[:, 32:32 + W_PX].copy(), wall[:, 32 - SHIFT_PX:32 - SHIFT_PX + W_PX].copy()


def _errors_px(fe: KLTFrontend, ids0: np.ndarray, uv0: np.ndarray) -> np.ndarray:
    _, i0, i1 = np.intersect1d(ids0, fe.ids, return_indices=True)
    return fe.uv_px[i1] - (uv0[i0] + [SHIFT_PX, 0.0])


def test_a_guess_one_period_off_aliases_and_retrack_recovers_the_true_motion() -> None:
    prev, cur = _facade_pair()
    cam = PinholeCamera(fx_px=359.0, fy_px=359.0, cx_px=W_PX / 2 - 0.5, cy_px=H_PX / 2 - 0.5,
                        width_px=W_PX, height_px=H_PX)
    fe = KLTFrontend(VOConfig.preset("synth"), cam)
    fe.detect(prev)
    fe.track(prev)
    ids0, uv0 = fe.ids.copy(), fe.uv_px.copy()
    assert len(ids0) > 100
    fe.track(cur, uv0 + [SHIFT_PX - PERIOD_PX, 0.0])  # the guess: one window period short
    err = _errors_px(fe, ids0, uv0)
    assert len(err) > 0.8 * len(ids0)  # the forward-backward check kept them ...
    assert np.mean(np.abs(err[:, 0] + PERIOD_PX) < 2.0) > 0.9  # ... a period off, all agreeing
    aliased = fe.tracks
    fe.retrack(cur)
    err = _errors_px(fe, ids0, uv0)
    assert len(err) > 0.8 * len(ids0)
    assert np.mean(np.linalg.norm(err, axis=1) < 1.0) > 0.95
    fe.restore(aliased)
    assert np.array_equal(fe.ids, aliased.ids) and np.array_equal(fe.uv_px, aliased.uv_px)


def test_retrack_needs_a_tracked_frame() -> None:
    cam = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=31.5, cy_px=31.5, width_px=64, height_px=64)
    assert KLTFrontend(VOConfig.preset("synth"), cam).retrack(np.zeros((64, 64), np.uint8)) is None


def test_two_high_frames_in_a_row_make_the_second_suspect() -> None:
    s = SuspectFrames(0.22)
    shares = {10: 0.5, 11: 0.1, 12: 0.3, 13: 0.3, 14: 0.9, 15: 0.22, 16: 0.23, 17: 0.4}
    flagged = [i for i, share in shares.items() if s.update(i, share)]
    assert flagged == [13, 14, 17]  # 10 alone is not enough; 0.22 itself is not above the threshold
    assert s.count == 3 and s.ranges == [[13, 14], [17, 17]]
    assert describe_ranges(s.ranges) == "13-14, 17"


def test_a_tracking_loss_breaks_the_pair_and_the_ranges_are_bounded() -> None:
    s = SuspectFrames(0.2, max_ranges=2)
    assert not s.update(0, 0.5)
    s.interrupt()
    assert not s.update(1, 0.5)  # its predecessor was before the loss
    assert s.update(2, 0.5)
    flagged = [i for i, share in ((3, 0.0), (5, 0.5), (6, 0.5), (7, 0.0), (9, 0.5), (10, 0.5)) if s.update(i, share)]
    assert flagged == [6, 10] and s.count == 3
    assert s.ranges == [[2, 2], [6, 6]]  # counting goes on past the kept ranges


@pytest.mark.slow
def test_the_rendered_loop_that_aliased_is_reported_without_the_retrack_and_fixed_with_it(
        synth_sequence, tmp_path, capsys) -> None:
    """Development worlds of the rules (620x188, 150 frames): seed 48 went 14 m wrong on ~130 m
    (Sim(3) ATE, ``--no-scale``) from frame 108, where a turn starts, with no loss reported; seed 44
    drives the same kind of turns cleanly (0.12 m). Without the re-track the bad run's suspect
    frames are reported, and reporting changes no pose (byte-identical with the report off too);
    with it (the default) the run keeps its shape (measured 0.145 m)."""
    no_retrack = "vo:\n  retrack_reject_share: 1.0\n"
    configs = {"default": "", "no_retrack": no_retrack, "nothing": no_retrack + "  suspect_reject_share: 1.0\n"}
    ate, stats = {}, {}
    for seed in (48, 44):
        seq = synth_sequence(150, seed=seed, path="loop")
        gt = read_kitti_poses(seq / "poses" / "00.txt")
        for name, text in configs.items():
            out = tmp_path / f"s{seed}_{name}.txt"
            extra = []
            if text:
                (tmp_path / f"{name}.yaml").write_text(text)
                extra = ["--config", str(tmp_path / f"{name}.yaml")]
            assert main(["run", str(seq), "--out", str(out), "--json", str(out.with_suffix(".json")),
                         "--deterministic", "--no-progress", "--no-scale", *extra]) == 0
            stats[seed, name] = json.loads(out.with_suffix(".json").read_text())
            _, aligned = align_trajectory(read_kitti_poses(out), gt)
            ate[seed, name] = float(np.sqrt(np.mean(np.sum((aligned[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=1))))
        assert (tmp_path / f"s{seed}_no_retrack.txt").read_bytes() == (tmp_path / f"s{seed}_nothing.txt").read_bytes()
        assert stats[seed, "nothing"]["vo_suspect_frames"] == 0 and stats[seed, "no_retrack"]["retracks"] == 0
    printed = capsys.readouterr().out
    bad = stats[48, "no_retrack"]
    assert ate[48, "no_retrack"] > 3.0, ate  # the scenario still aliases without the re-track
    assert bad["tracking_losses"] == 0 and bad["vo_suspect_frames"] >= 3
    assert 105 <= bad["vo_suspect_ranges"][0][0] <= 112, bad["vo_suspect_ranges"]
    assert f"warning: {bad['vo_suspect_frames']} frames whose VO tracks may be aliased" in printed
    assert ate[48, "default"] < 1.0 and stats[48, "default"]["retracks_kept"] >= 1, ate
    assert stats[44, "default"]["vo_suspect_frames"] == 0 and ate[44, "default"] < 0.3, ate


def test_kitti_06_has_no_suspect_frame(shared_data, tmp_path) -> None:
    seq = shared_data / "kitti_odometry" / "sequences" / "06"
    out = tmp_path / "06.txt"
    assert main(["run", str(seq), "--out", str(out), "--json", str(tmp_path / "06.json"),
                 "--deterministic", "--no-progress", "--no-scale"]) == 0
    stats = json.loads((tmp_path / "06.json").read_text())
    assert stats["vo_suspect_frames"] == 0 and stats["vo_suspect_ranges"] == []
