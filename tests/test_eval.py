"""The evaluator: KITTI devkit semantics on hand-computed cases, cross-checks against evo."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from metricslam.errors import EvaluationError
from metricslam.evaluation import build_report, evaluate_poses, evaluate_timed
from metricslam.evaluation.associate import associate
from metricslam.evaluation.kitti_metric import (
    KITTI_LENGTHS_M,
    kitti_segment_errors,
    segment_errors,
    trajectory_distances,
)
from metricslam.geometry import align, se3, sim3, so3


# ---------------------------------------------------------------- trajectories for the tests

def straight_line(n: int, step_m: float = 1.0) -> np.ndarray:
    """Camera driving forward along +z, ``step_m`` per frame, identity rotations (N, 4, 4)."""
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 2, 3] = np.arange(n) * step_m
    return T


def scaled(T: np.ndarray, s: float) -> np.ndarray:
    out = T.copy()
    out[:, :3, 3] *= s
    return out


def drive(n: int, seed: int) -> np.ndarray:
    """A car-like trajectory: forward 0.8..1.2 m per frame, slowly varying yaw, small pitch/roll."""
    rng = np.random.default_rng(seed)
    T = [np.eye(4)]
    yaw_rate = 0.0
    for _ in range(n - 1):
        yaw_rate = 0.95 * yaw_rate + rng.normal(0.0, 0.004)
        step = se3.exp(np.array([rng.normal(0, 0.002), yaw_rate, rng.normal(0, 0.002),
                                 rng.normal(0, 0.02), rng.normal(0, 0.01), rng.uniform(0.8, 1.2)]))
        T.append(T[-1] @ step)
    return np.stack(T)


def perturb(T_gt: np.ndarray, seed: int, scale: float = 1.03, drift: float = 1e-4,
            rot_sigma_rad: float = 2e-4) -> np.ndarray:
    """Chain the ground-truth relative motions with scale drift and rotation noise."""
    rng = np.random.default_rng(seed)
    est = [np.eye(4)]
    for i in range(1, len(T_gt)):
        rel = np.linalg.inv(T_gt[i - 1]) @ T_gt[i]
        rel[:3, 3] *= scale * (1.0 + drift * i)
        rel[:3, :3] = rel[:3, :3] @ so3.exp(rng.normal(0.0, rot_sigma_rad, 3))
        est.append(est[-1] @ rel)
    return np.stack(est)


def devkit_reference(gt: np.ndarray, est: np.ndarray, lengths=KITTI_LENGTHS_M):
    """A line-by-line port of the devkit's loops (no vectorisation), for comparison."""
    dist = [0.0]
    for i in range(1, len(gt)):
        dist.append(dist[i - 1] + math.sqrt(sum((gt[i - 1][k, 3] - gt[i][k, 3]) ** 2 for k in range(3))))
    errs = []
    for first in range(0, len(gt), 10):
        for L in lengths:
            last = -1
            for i in range(first, len(dist)):
                if dist[i] > dist[first] + L:
                    last = i
                    break
            if last == -1:
                continue
            E = np.linalg.inv(np.linalg.inv(est[first]) @ est[last]) @ (np.linalg.inv(gt[first]) @ gt[last])
            d = 0.5 * (E[0, 0] + E[1, 1] + E[2, 2] - 1.0)
            errs.append((first, last, L, math.sqrt(E[0, 3] ** 2 + E[1, 3] ** 2 + E[2, 3] ** 2) / L,
                         math.acos(max(min(d, 1.0), -1.0)) / L))
    return errs


# ---------------------------------------------------------------- hand-computed segment cases

def test_scaled_straight_line_end_frame_is_strictly_beyond_the_length():
    """1 m steps: dist[f+100] = dist[f] + 100 exactly, so the end frame is f+101, and the
    error 0.1·101 m is divided by L = 100 m (not by the driven 101 m): t_rel = 10.1 %."""
    gt = straight_line(201)
    seg = segment_errors(gt, scaled(gt, 1.1))
    assert len(seg) == 10  # start frames 0, 10, …, 90; no 200 m segment fits in 200 m
    assert seg.first_frame.tolist() == list(range(0, 100, 10))
    assert (seg.last_frame - seg.first_frame).tolist() == [101] * 10
    assert seg.used_lengths_m == [100.0]
    assert seg.t_rel_pct == pytest.approx(10.1, abs=1e-9)
    assert seg.r_rel_deg_per_100m == pytest.approx(0.0, abs=1e-6)


def test_rotation_drift_gives_angle_over_length():
    """Estimate yaws α rad more each frame: every 100 m segment (101 frames) is off by 101·α."""
    alpha = 1e-4
    gt = straight_line(201)
    est = gt.copy()
    for i in range(201):
        est[i, :3, :3] = so3.exp(np.array([0.0, alpha * i, 0.0]))
    seg = segment_errors(gt, est)
    assert seg.r_rel_deg_per_100m == pytest.approx(np.degrees(alpha * 101 / 100) * 100, rel=1e-6)


def test_short_sequence_falls_back_to_10_to_50_m():
    """30 frames of 1 m: L=10 fits at f=0,10 and L=20 at f=0 (each 0.1·(L+1)/L error)."""
    gt = straight_line(31)
    seg = kitti_segment_errors(gt, scaled(gt, 1.1))
    assert seg.used_lengths_m == [10.0, 20.0]
    assert len(seg) == 3
    assert seg.t_rel_pct == pytest.approx(100 * np.mean([0.11, 0.11, 0.105]), abs=1e-9)
    res = evaluate_poses(gt, scaled(gt, 1.1)).result
    assert res.short_sequence and res.t_rel_lengths_m == [10.0, 20.0]
    assert any("10..50 m" in n for n in res.notes)


def test_too_short_for_any_segment_gives_null_with_a_note():
    T = drive(6, seed=1)
    res = evaluate_poses(T, T).result
    assert res.t_rel_pct is None and res.r_rel_deg_per_100m is None and res.t_rel_lengths_m == []
    assert any("undefined" in n for n in res.notes)
    assert json.loads(json.dumps(res.model_dump(mode="json")))["t_rel_pct"] is None


def test_long_sequence_uses_the_devkit_lengths_that_fit():
    gt = drive(700, seed=2)  # ~700 m
    res = evaluate_poses(gt, perturb(gt, 3)).result
    assert not res.short_sequence
    assert res.t_rel_lengths_m == [L for L in KITTI_LENGTHS_M if L < trajectory_distances(gt)[-1]]


@pytest.mark.parametrize("seed", [0, 1])
def test_vectorised_segments_equal_a_literal_port_of_the_devkit(seed):
    gt = drive(450, seed)
    est = perturb(gt, seed + 10, scale=0.97, drift=3e-4, rot_sigma_rad=1e-3)
    ours = segment_errors(gt, est, lengths_m=(50.0, 100.0, 200.0, 400.0))
    ref = np.array(devkit_reference(gt, est, lengths=(50.0, 100.0, 200.0, 400.0)))
    assert len(ours) == len(ref) > 0
    assert np.array_equal(ours.first_frame, ref[:, 0]) and np.array_equal(ours.last_frame, ref[:, 1])
    assert np.allclose(ours.t_err_per_m, ref[:, 3], rtol=1e-12, atol=1e-15)
    assert np.allclose(ours.r_err_rad_per_m, ref[:, 4], rtol=1e-9, atol=1e-12)


def test_metrics_of_a_perfect_estimate_are_zero_and_scale_is_one():
    gt = drive(300, seed=4)
    res = evaluate_poses(gt, gt).result
    assert res.t_rel_pct == pytest.approx(0.0, abs=1e-9)
    assert res.r_rel_deg_per_100m == pytest.approx(0.0, abs=1e-3)  # acos near 1 (devkit formula)
    assert res.ate_rmse_m == pytest.approx(0.0, abs=1e-9)
    assert res.scale_ratio == pytest.approx(1.0) and res.scale_error_pct == pytest.approx(0.0, abs=1e-9)


def test_global_scale_is_reported_as_estimate_over_truth_and_removed_by_sim3():
    gt = drive(300, seed=5)
    res = evaluate_poses(gt, scaled(gt, 1.25)).result
    assert res.scale_ratio == pytest.approx(1.25, rel=1e-9)
    assert res.scale_error_pct == pytest.approx(25.0, rel=1e-7)
    assert res.ate_rmse_sim3_m == pytest.approx(0.0, abs=1e-8)
    assert res.ate_rmse_m > 1.0
    # |trans(E)| = 0.25·|p_l − p_f| (the chord, shorter than the driven length) for every segment
    assert res.t_rel_pct == pytest.approx(25.0 * mean_chord_over_length(gt), rel=1e-9)


def mean_chord_over_length(gt: np.ndarray) -> float:
    seg = kitti_segment_errors(gt, gt)
    chord = np.linalg.norm(gt[seg.last_frame, :3, 3] - gt[seg.first_frame, :3, 3], axis=1)
    return float(np.mean(chord / seg.length_m))


def test_relative_metrics_ignore_the_estimate_world_frame_but_unaligned_ate_does_not():
    gt = drive(250, seed=6)
    est = perturb(gt, seed=7)
    moved = np.einsum("ij,njk->nik", se3.exp(np.array([0.3, -0.2, 0.5, 4.0, 1.0, -7.0])), est)
    a, b = evaluate_poses(gt, est).result, evaluate_poses(gt, moved).result
    for key in ("t_rel_pct", "r_rel_deg_per_100m", "ate_rmse_m", "ate_rmse_sim3_m", "scale_ratio",
                "rpe_trans_rmse_m", "rpe_rot_rmse_deg"):
        assert getattr(a, key) == pytest.approx(getattr(b, key), rel=1e-6, abs=1e-9), key
    assert b.ate_rmse_unaligned_m > a.ate_rmse_unaligned_m + 1.0


def test_straight_line_ground_truth_still_gives_t_rel_with_null_alignment():
    gt = straight_line(60)
    res = evaluate_poses(gt, scaled(gt, 1.1)).result
    assert res.t_rel_pct is not None and res.ate_rmse_m is None and res.scale_ratio is None
    assert any("undefined" in n for n in res.notes)


def test_mismatched_or_broken_inputs_raise_evaluation_error():
    gt = drive(50, seed=8)
    with pytest.raises(EvaluationError, match="one\\s+pose per ground-truth frame"):
        evaluate_poses(gt, gt[:-1])
    with pytest.raises(EvaluationError, match="at least 3"):
        evaluate_poses(gt[:2], gt[:2])
    bad = gt.copy()
    bad[5, 0, 3] = np.nan
    with pytest.raises(EvaluationError, match="NaN"):
        evaluate_poses(gt, bad)


# ---------------------------------------------------------------- pooling

def test_pooled_is_over_all_segments_and_mean_is_over_sequences():
    ev = []
    for seed, n in ((11, 350), (12, 600)):
        gt = drive(n, seed)
        ev.append(evaluate_poses(gt, perturb(gt, seed, scale=1.0 + 0.01 * seed % 7, drift=2e-4),
                                 name=f"s{seed}"))
    rep = build_report(ev)
    segs = [e.segments for e in ev]
    pooled_t = 100 * np.mean(np.concatenate([s.t_err_per_m for s in segs]))
    assert rep.pooled.t_rel_pct == pytest.approx(pooled_t)
    assert rep.mean_of_sequences.t_rel_pct == pytest.approx(np.mean([e.result.t_rel_pct for e in ev]))
    assert rep.pooled.n_frames == 950 and rep.pooled.n_segments == sum(len(s) for s in segs)
    # pooled ATE is the RMSE over all frames of both sequences
    sq = np.concatenate([e.ate.err_se3_m ** 2 for e in ev])
    assert rep.pooled.ate_rmse_m == pytest.approx(np.sqrt(sq.mean()))
    out = rep.to_json_dict()
    assert out["t_rel_pct"] == rep.pooled.t_rel_pct and len(out["per_sequence"]) == 2


def test_single_sequence_json_has_exactly_the_contract_keys_at_top_level():
    gt = drive(200, seed=13)
    out = build_report([evaluate_poses(gt, perturb(gt, 13))]).to_json_dict()
    for key in ("t_rel_pct", "r_rel_deg_per_100m", "ate_rmse_m", "ate_rmse_sim3_m", "scale_ratio",
                "scale_error_pct", "n_frames", "path_length_m", "t_rel_lengths_m"):
        assert key in out, key
    assert "per_sequence" not in out
    assert out["path_length_m"] == pytest.approx(trajectory_distances(gt)[-1])


# ---------------------------------------------------------------- association

def test_association_nearest_within_tolerance_and_one_to_one():
    t_gt = np.array([0, 100, 200, 300, 400]) * 1_000_000
    t_est = np.array([5, 95, 101, 260, 900]) * 1_000_000
    i_gt, i_est = associate(t_gt, t_est, max_diff_ns=20_000_000)
    assert list(zip(i_gt.tolist(), i_est.tolist())) == [(0, 0), (1, 2)]
    with pytest.raises(EvaluationError, match="no estimate timestamp"):
        associate(t_gt, t_est + 10**10)


# ---------------------------------------------------------------- cross-check against evo

def _evo_numbers(gt: np.ndarray, est: np.ndarray) -> dict:
    import copy

    from evo.core import metrics
    from evo.core.trajectory import PosePath3D
    from evo.core.units import Unit

    ref = PosePath3D(poses_se3=list(gt))

    def ape(traj) -> float:
        m = metrics.APE(metrics.PoseRelation.translation_part)
        m.process_data((ref, traj))
        return m.get_statistic(metrics.StatisticsType.rmse)

    raw = PosePath3D(poses_se3=list(est))
    se3_traj = copy.deepcopy(raw)
    se3_traj.align(ref, correct_scale=False)
    sim3_traj = copy.deepcopy(raw)
    _, _, s = sim3_traj.align(ref, correct_scale=True)
    out = {"unaligned": ape(raw), "se3": ape(se3_traj), "sim3": ape(sim3_traj), "s": s}
    for rel, key in ((metrics.PoseRelation.translation_part, "rpe_t"),
                     (metrics.PoseRelation.rotation_angle_deg, "rpe_r")):
        m = metrics.RPE(rel, delta=1, delta_unit=Unit.frames, all_pairs=False)
        m.process_data((ref, raw))
        out[key] = m.get_statistic(metrics.StatisticsType.rmse)
    return out


@pytest.mark.parametrize("seed", [21, 22])
def test_ate_rpe_and_scale_match_evo(seed):
    gt = drive(400, seed)
    est = perturb(gt, seed, scale=1.05, drift=2e-4, rot_sigma_rad=5e-4)
    res = evaluate_poses(gt, est).result
    evo = _evo_numbers(gt, est)
    assert res.ate_rmse_unaligned_m == pytest.approx(evo["unaligned"], rel=1e-9)
    assert res.ate_rmse_m == pytest.approx(evo["se3"], rel=1e-7)
    assert res.ate_rmse_sim3_m == pytest.approx(evo["sim3"], rel=1e-7)
    assert res.scale_ratio == pytest.approx(1.0 / evo["s"], rel=1e-9)
    assert res.rpe_trans_rmse_m == pytest.approx(evo["rpe_t"], rel=1e-7)
    assert res.rpe_rot_rmse_deg == pytest.approx(evo["rpe_r"], rel=1e-5)


def test_timed_evaluation_matches_evo_after_association():
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    gt = drive(300, seed=31)
    est = perturb(gt, 31)
    t_gt = 1_600_000_000_000_000_000 + np.arange(300, dtype=np.int64) * 100_000_000
    # the estimate is stamped with 3 ms jitter and misses every 7th frame
    keep = np.arange(300) % 7 != 3
    rng = np.random.default_rng(31)
    t_est = t_gt[keep] + rng.integers(-3_000_000, 3_000_000, keep.sum())
    ev = evaluate_timed(t_gt, gt, t_est, est[keep])
    assert ev.result.n_frames == keep.sum()

    ref = PoseTrajectory3D(poses_se3=list(gt), timestamps=t_gt / 1e9)
    tr = PoseTrajectory3D(poses_se3=list(est[keep]), timestamps=t_est / 1e9)
    ref, tr = sync.associate_trajectories(ref, tr, max_diff=0.01)
    tr.align(ref, correct_scale=False)
    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((ref, tr))
    assert ev.result.ate_rmse_m == pytest.approx(m.get_statistic(metrics.StatisticsType.rmse), rel=1e-7)


def test_ate_of_a_known_sim3_displacement():
    """Estimate = ground truth seen through an exact Sim(3): aligned errors vanish, scale inverts."""
    gt = drive(120, seed=41)
    S = sim3.from_rts(so3.exp(np.array([0.2, 0.1, -0.3])), np.array([3.0, -1.0, 2.0]), 0.5)
    est = align.apply_to_poses(S, gt)
    res = evaluate_poses(gt, est).result
    assert res.scale_ratio == pytest.approx(0.5) and res.ate_rmse_sim3_m == pytest.approx(0, abs=1e-8)
    assert res.t_rel_pct == pytest.approx(50.0 * mean_chord_over_length(gt), rel=1e-9)
    assert res.r_rel_deg_per_100m == pytest.approx(0.0, abs=1e-3)


def test_plot_writes_a_png(tmp_path):
    from metricslam.evaluation.plots import save_plot, top_view_axes

    gt = drive(150, seed=51)
    ev = evaluate_poses(gt, perturb(gt, 51), name="x")
    out = save_plot([ev, evaluate_poses(straight_line(40), straight_line(40))], tmp_path / "p.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert top_view_axes(gt[:, :3, 3]) == (0, 2)  # KITTI-like: y (down) is dropped


@pytest.mark.data
def test_real_kitti07_ground_truth_against_a_perturbed_copy_matches_evo(shared_data):
    from metricslam.trajectory.io import read_kitti_poses

    gt = read_kitti_poses(shared_data / "kitti_gt_poses_full" / "07.txt")
    est = perturb(gt, seed=7, scale=1.02, drift=5e-5, rot_sigma_rad=2e-4)
    res = evaluate_poses(gt, est, name="07").result
    evo = _evo_numbers(gt, est)
    assert res.n_frames == 1101 and res.path_length_m == pytest.approx(694.7, abs=0.1)
    assert res.t_rel_lengths_m == [100.0, 200.0, 300.0, 400.0, 500.0, 600.0]
    assert res.ate_rmse_m == pytest.approx(evo["se3"], rel=1e-7)
    assert res.ate_rmse_sim3_m == pytest.approx(evo["sim3"], rel=1e-7)
    assert res.scale_ratio == pytest.approx(1.0 / evo["s"], rel=1e-9)
    assert res.rpe_trans_rmse_m == pytest.approx(evo["rpe_t"], rel=1e-7)
    assert 1.0 < res.t_rel_pct < 10.0
