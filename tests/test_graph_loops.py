"""Loop factors in the global graph: a correct loop removes drift, a false one cannot wreck it."""

from __future__ import annotations

import numpy as np
from graph_chain import FAST_DRIFT, add_odometry_keyframe
from metricslam.geometry import sim3
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.sim3_graph import GlobalPoseGraph
from metricslam.slam.graph.synthetic import SimulatedVO, circle_path

N = 80


def _drifting_circle(seed: int = 5) -> tuple[GlobalPoseGraph, SimulatedVO, np.ndarray]:
    """A closed circle driven by a VO whose scale drifts 1 %/keyframe, no scale factors."""
    cfg = GraphConfig(**FAST_DRIFT)
    T = circle_path(N, 40.0, turns=1.0 * (N - 1) / N)  # last keyframe just before the start
    vo = SimulatedVO(T, drift_per_kf=0.01, drift_noise=0.004, seed=seed)
    graph = GlobalPoseGraph(cfg, anchor_scale=True)
    S_true = []
    prev = None
    for _ in range(N):
        kf = vo.next_keyframe()
        S_true.append(sim3.from_se3(T[kf.kf_id], vo.sigma_at_kf[-1]))
        add_odometry_keyframe(graph, prev, kf, cfg)
        graph.solve()
        prev = kf
    return graph, vo, np.array(S_true)


def _position_errors(graph: GlobalPoseGraph, T_true: np.ndarray) -> np.ndarray:
    est = graph.estimates()
    p = np.array([est[k][:3, 3] for k in range(N)])
    return np.linalg.norm(p - T_true[:, :3, 3], axis=1)


def _loop_sigmas(S_old_new: np.ndarray) -> np.ndarray:
    return np.array([0.01] * 3 + [max(0.05 * np.linalg.norm(S_old_new[:3, 3]), 0.05)] * 3 + [0.05])


def test_correct_loop_removes_drift():
    graph, vo, S_true = _drifting_circle()
    before = _position_errors(graph, vo.T_true)
    assert before[-1] > 10.0  # drift: the circle does not close
    S_meas = sim3.inverse(S_true[0]) @ S_true[-1]
    decision = graph.add_loop(0, N - 1, S_meas, _loop_sigmas(S_meas))
    assert decision.accepted, decision
    graph.solve()
    after = _position_errors(graph, vo.T_true)
    assert after[-1] < 0.1 * before[-1]
    assert after.max() < 0.35 * before.max()
    assert graph.n_loops == 1


def test_false_loop_between_distant_places_is_rejected():
    graph, _, S_true = _drifting_circle()
    before = graph.estimates()
    # claim the far side of the circle (80 m away) is where the last keyframe is
    S_fake = sim3.inverse(S_true[0]) @ S_true[-1]  # a correct measurement...
    decision = graph.add_loop(N // 2, N - 1, S_fake, _loop_sigmas(S_fake))  # ...on the wrong pair
    assert not decision.accepted
    graph.solve()
    after = graph.estimates()
    assert max(np.abs(after[k] - before[k]).max() for k in range(N)) < 1e-6


def test_forced_false_loop_does_not_wreck_the_map():
    """Even past the gate, a false loop is removed after the solve and the map comes back."""
    graph, vo, S_true = _drifting_circle()
    before = _position_errors(graph, vo.T_true)
    S_fake = sim3.inverse(S_true[0]) @ S_true[-1]
    decision = graph.add_loop(N // 2, N - 1, S_fake, _loop_sigmas(S_fake), gate=False)
    assert decision.accepted
    res = graph.solve()
    assert res["loops_removed"] == 1 and graph.n_loops == 0
    after = _position_errors(graph, vo.T_true)
    assert after.max() < 1.05 * before.max() + 0.5


def test_true_loop_survives_alongside_false_one():
    graph, vo, S_true = _drifting_circle()
    S_ok = sim3.inverse(S_true[0]) @ S_true[-1]
    assert graph.add_loop(0, N - 1, S_ok, _loop_sigmas(S_ok)).accepted
    graph.solve()
    S_fake = S_ok  # "these two are 3 m apart" about places 80 m apart
    graph.add_loop(N // 2, N - 2, S_fake, _loop_sigmas(S_fake), gate=False)
    graph.solve()
    assert graph.n_loops == 1
    assert _position_errors(graph, vo.T_true)[-1] < 2.0


def test_rebuild_from_batch_keeps_the_solution_and_the_loops():
    """The recovery path after a failed incremental step (ill-conditioned update)."""
    graph, _, S_true = _drifting_circle()
    S_ok = sim3.inverse(S_true[0]) @ S_true[-1]
    assert graph.add_loop(0, N - 1, S_ok, _loop_sigmas(S_ok)).accepted
    graph.solve()
    before = graph.estimates()
    graph._rebuild()
    after = graph.estimates()
    assert max(np.abs(after[k] - before[k]).max() for k in range(N)) < 0.05
    assert graph.n_loops == 1 and len(graph._loop_indices) == 1
    # incremental updates continue on the rebuilt ISAM2
    S_fake = S_ok
    graph.add_loop(N // 2, N - 2, S_fake, _loop_sigmas(S_fake), gate=False)
    assert graph.solve()["loops_removed"] == 1
