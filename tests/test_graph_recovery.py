"""Indeterminate ISAM2 updates: why a well-posed graph was reported indeterminate (gtsam's
Cholesky zero-pivot threshold vs. the far end of a long loop-free chain) and the recovery path
when an update does fail (it must not leave ISAM2 half-updated: "key already exists")."""

from __future__ import annotations

import numpy as np
import pytest
from graph_chain import add_odometry_keyframe
from metricslam.geometry import se3, sim3
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.odometry import odometry_information, relative_sim3
from metricslam.slam.graph.sim3_graph import GlobalPoseGraph
from metricslam.slam.graph.synthetic import SimulatedVO, circle_path


def _chain(T_world_kf: np.ndarray, n: int, cfg: GraphConfig, extra: int = 0) -> tuple[GlobalPoseGraph, list]:
    """The first ``n`` of ``n + extra`` drift-free simulated keyframes along ``T_world_kf`` as an
    odometry chain, solved after each; returns the graph and all ``n + extra`` keyframes."""
    vo = SimulatedVO(T_world_kf, drift_per_kf=0.0, drift_noise=0.0, seed=1)
    graph = GlobalPoseGraph(cfg, anchor_scale=True)
    kfs = [vo.next_keyframe() for _ in range(n + extra)]
    for prev, kf in zip([None] + kfs[:n - 1], kfs[:n]):
        add_odometry_keyframe(graph, prev, kf, cfg)
        graph.solve()
    return graph, kfs


def test_indeterminate_update_is_rebuilt_and_later_updates_work():
    cfg = GraphConfig(factorization="CHOLESKY")  # QR would not even notice the free direction
    graph, kfs = _chain(circle_path(22, 40.0, 0.5), 12, cfg, extra=3)
    before = graph.estimates()
    prev, bad = kfs[11], kfs[12]
    S = relative_sim3(prev.T_vo_kf, bad.T_vo_kf)
    info = odometry_information(S, None, cfg)
    info[6, 6] = 0.0  # the new keyframe's scale is constrained by nothing: ISAM2 cannot factor
    graph.add_keyframe(bad.kf_id, graph.estimate(prev.kf_id) @ S, prev.kf_id, S, info)
    graph.solve()  # must not raise: batch rebuild, weak prior on the indeterminate keyframe
    assert graph.n_rebuilds == 1 and graph.n_stabilized >= 1
    after = graph.estimates()
    assert max(np.abs(after[k] - before[k]).max() for k in before) < 1e-3  # old map unchanged
    assert np.allclose(after[bad.kf_id], before[prev.kf_id] @ S, atol=1e-3)
    # no "key already exists" afterwards: later keyframes go in incrementally
    for p, k in ((kfs[12], kfs[13]), (kfs[13], kfs[14])):
        S = relative_sim3(p.T_vo_kf, k.T_vo_kf)
        graph.add_keyframe(k.kf_id, graph.estimate(p.kf_id) @ S, p.kf_id, S, odometry_information(S, None, cfg))
        graph.solve()
    assert graph.n_rebuilds == 1 and graph.n_keyframes == 15
    assert np.isfinite(sim3.scale(graph.estimate(kfs[14].kf_id)))


def _straight_chain(n: int, cfg: GraphConfig) -> GlobalPoseGraph:
    T = np.array([se3.from_rt(np.eye(3), np.array([0.0, 0.0, 3.0 * i])) for i in range(n)])
    return _chain(T, n, cfg)[0]


def test_long_loop_free_chain_is_not_indeterminate():
    """1.2 km without a loop, 0.05 rad per step: the end is known to ~1 km sideways (information
    < 1e-6 per m²), which gtsam's Cholesky calls indeterminate; QR (the default) solves it."""
    qr = _straight_chain(400, GraphConfig(odom_sigma_rot_rad=0.05))
    assert qr.n_rebuilds == 0 and qr.n_stabilized == 0
    chol = _straight_chain(400, GraphConfig(odom_sigma_rot_rad=0.05, factorization="CHOLESKY"))
    assert chol.n_rebuilds >= 1  # what the synthetic 2 km drive hit around keyframe 910
    a, b = qr.estimates(), chol.estimates()
    assert max(np.linalg.norm(a[k][:3, 3] - b[k][:3, 3]) for k in a) < 0.05  # recovered, same map
    assert np.allclose(a[399][:3, 3], [0.0, 0.0, 1197.0], atol=0.05)


def test_a_rebuild_that_fails_leaves_the_committed_graph_and_keeps_the_pending_factors(monkeypatch):
    # the old ISAM2 is released before the batch solve (memory), so a failure must rebuild it
    from metricslam.errors import GraphError
    from metricslam.slam.graph import batch_solve

    cfg = GraphConfig()
    graph, kfs = _chain(circle_path(22, 40.0, 0.5), 10, cfg, extra=1)
    assert graph.solve()["batch"] is False  # incremental
    before, n_committed = graph.estimates(), graph.factor_graph().size()
    real = batch_solve.solve_batch

    def failing(*args, **kwargs):
        raise GraphError("simulated: no fresh ISAM2")

    monkeypatch.setattr(batch_solve, "solve_batch", failing)
    add_odometry_keyframe(graph, kfs[9], kfs[10], cfg)
    S_loop = relative_sim3(kfs[0].T_vo_kf, kfs[10].T_vo_kf)
    assert graph.add_loop(kfs[0].kf_id, kfs[10].kf_id, S_loop, np.array([0.01] * 3 + [0.1] * 3 + [0.05])).accepted
    with pytest.raises(GraphError, match="simulated"):
        graph.solve()
    after = graph.estimates()
    assert set(after) == set(before) | {kfs[10].kf_id}
    assert max(np.abs(after[k] - before[k]).max() for k in before) < 1e-9  # the committed map, as it was
    assert graph.factor_graph().size() == n_committed  # ... with every committed factor
    monkeypatch.setattr(batch_solve, "solve_batch", real)
    assert graph.solve()["batch"]  # the pending keyframe and loop go in now, in a batch re-solve
    assert graph.n_keyframes == 11 and graph.loop_pairs() == {(kfs[0].kf_id, kfs[10].kf_id)}
    assert graph.factor_graph().size() == n_committed + 2  # + the odometry and the loop
    assert np.allclose(graph.estimate(kfs[10].kf_id), before[kfs[9].kf_id] @ relative_sim3(kfs[9].T_vo_kf, kfs[10].T_vo_kf), atol=1e-3)
