"""The frames inside the VO's two-view start (``metricslam.slam.vo.initializer``;
``docs/history/rule_vo_init_pending_session22.md``).

Between the reference frame and the frame the two-view start succeeds on, the VO has no map to
track against; once it has one, each of those frames gets a pose by motion-only BA of its own tracks
against the two-view points (interpolating along the two-view motion is degrees off where a turn
starts between the views), and a start whose points do not explain those frames (tracks aliased at
a turn onset gave a wrong essential matrix) is reported as suspect frames, not rejected.
"""

from __future__ import annotations

import json
import logging

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.geometry import se3, so3
from metricslam.slam.vo.aliasing import SuspectFrames
from metricslam.slam.vo.config import VOConfig
from metricslam.slam.vo.initializer import InitRef, InitResult, pending_poses, start_confirmed
from metricslam_cli.main import main

CAM = PinholeCamera(fx_px=360.0, fy_px=360.0, cx_px=310.0, cy_px=94.0, width_px=620, height_px=188)
N_PTS, N_FRAMES = 200, 8  # frames 1..7 between the reference 0 and the start frame 8


def _turning_start(seed: int = 0):
    """Points 6-30 m ahead; the camera drives 0.8 m/frame straight for 5 frames, then turns
    3°/frame: ``(p_ref (N, 3), T_ref_f (N_FRAMES + 1, 4, 4))``, frame 0 the reference."""
    poses, yaw, pos = [], 0.0, np.zeros(3)
    for k in range(N_FRAMES + 1):
        if k > 5:
            yaw += np.radians(3.0)
        if k > 0:
            pos = pos + so3.exp(np.array([0.0, yaw, 0.0])) @ np.array([0.0, 0.0, 0.8])
        poses.append(se3.from_rt(so3.exp(np.array([0.0, yaw, 0.0])), pos))
    rng = np.random.default_rng(seed)
    p = np.c_[rng.uniform(-15, 15, 4 * N_PTS), rng.uniform(-3, 2, 4 * N_PTS), rng.uniform(12, 40, 4 * N_PTS)]
    seen = np.ones(len(p), bool)
    for T in poses:  # in view in every frame
        uv = _pixels(p, T)
        seen &= np.isfinite(uv).all(axis=1) & (uv[:, 0] > 0) & (uv[:, 0] < 620) & (uv[:, 1] > 0) & (uv[:, 1] < 188)
    assert seen.sum() >= N_PTS
    return p[seen][:N_PTS], np.array(poses)


def _pixels(p_ref: np.ndarray, T_ref_f: np.ndarray) -> np.ndarray:
    T_f_ref = se3.inverse(T_ref_f)
    return CAM.project(p_ref @ T_f_ref[:3, :3].T + T_f_ref[:3, 3])


def _start(p_ref, poses, pending_uv=None):
    """The ``InitRef`` (tracks of every frame in between) and the exact ``InitResult`` (|t| = 1)."""
    ids = np.arange(N_PTS)
    uv = [_pixels(p_ref, T) for T in poses]
    if pending_uv is not None:
        uv[1:-1] = pending_uv
    pending = [(k, k * 100_000_000, ids, uv[k]) for k in range(1, N_FRAMES)]
    ref = InitRef(0, 0, np.zeros((188, 620), np.uint8), ids, uv[0], np.eye(4), pending)
    T_ref_cur = poses[-1].copy()
    unit = np.linalg.norm(T_ref_cur[:3, 3])
    T_ref_cur[:3, 3] /= unit
    res = InitResult(T_ref_cur, ids, unit / p_ref[:, 2], 3.0)  # inverse depths in units of |t| = 1
    return ref, res, poses[-1], N_FRAMES * 100_000_000


def test_frames_between_the_views_are_posed_where_interpolation_is_degrees_off() -> None:
    p_ref, poses = _turning_start()
    ref, res, T_ref_cur, t_cur_ns = _start(p_ref, poses)
    out = pending_poses(CAM, VOConfig(), ref, res, T_ref_cur, t_cur_ns)
    assert [k for k, _, _ in out] == list(range(1, N_FRAMES))
    w = so3.log(T_ref_cur[:3, :3])
    for k, T, share in out:
        interpolated = so3.exp(k / N_FRAMES * w)
        off_interp = np.degrees(so3.angle(interpolated.T @ poses[k][:3, :3]))
        off = np.degrees(so3.angle(T[:3, :3].T @ poses[k][:3, :3]))
        assert off < 0.05 and np.linalg.norm(T[:3, 3] - poses[k][:3, 3]) < 0.01, (k, off)
        assert share > 0.99
        if k == 5:  # the turn starts after frame 5: interpolation spreads it over every frame
            assert off_interp > 1.0, off_interp
    assert start_confirmed(VOConfig(), out, 0, N_FRAMES)


def test_a_start_its_frames_do_not_explain_is_not_confirmed(caplog) -> None:
    p_ref, poses = _turning_start()
    rng = np.random.default_rng(1)
    uv = [_pixels(p_ref, T) for T in poses]
    # frame 4's tracks: 40 % of them moved 25 px (aliased one window period away)
    bad = rng.choice(N_PTS, int(0.4 * N_PTS), replace=False)
    uv[4][bad, 0] += 25.0
    ref, res, T_ref_cur, t_cur_ns = _start(p_ref, poses, uv[1:-1])
    out = pending_poses(CAM, VOConfig(), ref, res, T_ref_cur, t_cur_ns)
    shares = {k: s for k, _, s in out}
    assert shares[4] < 0.7 and min(s for k, s in shares.items() if k != 4) > 0.99, shares
    with caplog.at_level(logging.WARNING, logger="metricslam.slam.vo.initializer"):
        assert not start_confirmed(VOConfig(), out, 0, N_FRAMES)
    assert "two-view start from frame 0 does not explain the frames between" in caplog.text
    assert start_confirmed(VOConfig(init_pending_min_share=0.5), out, 0, N_FRAMES)


def test_too_few_points_keep_the_interpolated_pose() -> None:
    p_ref, poses = _turning_start()
    ref, res, T_ref_cur, t_cur_ns = _start(p_ref, poses)
    few = [(k, t, ids[:10], uv[:10]) for k, t, ids, uv in ref.pending]
    ref = InitRef(0, 0, ref.image, ref.ids, ref.uv_px, np.eye(4), few)
    out = pending_poses(CAM, VOConfig(), ref, res, T_ref_cur, t_cur_ns)
    w = so3.log(T_ref_cur[:3, :3])
    for k, T, share in out:
        assert np.isnan(share) and np.allclose(T[:3, :3], so3.exp(k / N_FRAMES * w))
    assert start_confirmed(VOConfig(), out, 0, N_FRAMES)  # nothing to judge it by


def test_marked_ranges_merge_with_adjacent_ones_and_count_every_frame() -> None:
    s = SuspectFrames(0.22)
    s.mark(0, 8)
    s.update(9, 0.5)
    assert s.update(10, 0.5)
    s.mark(11, 12)  # a start right after a suspect frame: one range
    assert s.ranges == [[0, 8], [10, 12]] and s.count == 12
    s.mark(20, 22)
    assert s.ranges == [[0, 8], [10, 12], [20, 22]] and s.count == 15


def test_the_rendered_loop_whose_start_went_wrong_is_reported(synth_sequence, tmp_path, capsys) -> None:
    """Development world of the rule (620x188, seed 112): the two-view start over frames 0-8, as a
    turn begins, estimated 25.5° of rotation where the camera turned 6.3°, and nothing said so.
    It is reported now (measured: 0.51 of a frame's points agree); seed 105's right start, with a
    turn inside its window too, is not."""
    stats = {}
    for seed in (112, 105):
        seq = synth_sequence(150, seed=seed, path="loop")
        out = tmp_path / f"s{seed}.txt"
        assert main(["run", str(seq), "--out", str(out), "--json", str(out.with_suffix(".json")),
                     "--deterministic", "--no-progress", "--no-scale"]) == 0
        stats[seed] = json.loads(out.with_suffix(".json").read_text())
    printed = capsys.readouterr().out
    assert stats[112]["vo_suspect_ranges"][0] == [0, 8], stats[112]["vo_suspect_ranges"]
    assert "warning: " in printed and "(frames 0-8" in printed
    assert all(r[0] > 15 for r in stats[105]["vo_suspect_ranges"]), stats[105]["vo_suspect_ranges"]
