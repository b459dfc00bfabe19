"""Scale factors (eq. 12), gauge freedom and scale recovery of the global Sim(3) graph."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from graph_chain import FAST_DRIFT, add_odometry_keyframe
from hypothesis import given, settings
from hypothesis import strategies as st
from metricslam.geometry import sim3
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.gtsam_sim3 import from_gtsam, key, to_gtsam
from metricslam.slam.graph.scale_factor import (
    log_scale_residual,
    make_scale_factors,
    robust_log_scale,
    scale_measurements,
    scale_noise,
    with_scale,
)
from metricslam.slam.graph.sim3_graph import GlobalPoseGraph
from metricslam.slam.graph.synthetic import (
    SimulatedVO,
    SyntheticDepthSource,
    circle_path,
)

finite = st.floats(-2.0, 2.0, allow_nan=False)


@given(st.lists(finite, min_size=7, max_size=7), st.floats(-2.0, 2.0))
@settings(max_examples=50, deadline=None)
def test_lambda_component_is_log_scale_ratio(zeta, log_s_meas):
    S = gtsam.Similarity3.Expmap(np.array(zeta))
    S_prior = with_scale(S, float(np.exp(log_s_meas)))
    assert S_prior.scale() == pytest.approx(np.exp(log_s_meas), rel=1e-9)
    lam = log_scale_residual(S_prior, S)
    assert lam == pytest.approx(np.log(S.scale()) - log_s_meas, abs=1e-9)
    # the other six components vanish: the prior only talks about scale
    full = gtsam.Similarity3.Logmap(S_prior.inverse().compose(S))
    assert np.abs(full[:6]).max() < 1e-9


def test_scale_factor_jacobian_only_on_lambda():
    S = gtsam.Similarity3.Expmap(np.array([0.1, -0.2, 0.3, 1.0, 2.0, -1.0, 0.4]))
    s_meas = S.scale() * 1.05  # inside the Huber threshold: plain least squares
    (f,) = make_scale_factors(key(0), S, np.array([s_meas]), scale_noise(GraphConfig()))
    v = gtsam.Values()
    v.insert(key(0), S)
    A, b = f.linearize(v).jacobian()
    sigma = GraphConfig().scale_sigma_log
    assert np.abs(A[6, :6]).max() < 1e-12 and A[6, 6] == pytest.approx(1.0 / sigma, rel=1e-6)
    assert np.abs(A[:6]).max() < 1e-3  # 1/1e4: no information on rotation/translation
    assert -b[6] * sigma == pytest.approx(np.log(S.scale() / s_meas), rel=1e-6)


def test_scale_measurements_filter_and_ratio():
    cfg = GraphConfig(max_scale_landmarks=3)
    xi = np.array([0.2, 0.4, np.nan, 0.3, -1.0, 0.5, 0.1])
    z = np.array([0.1, 0.1, 0.1, 1e-6, 0.1, 0.25, 0.05])
    s = scale_measurements(xi, z, cfg)
    # nan, too-far (1e-6 < min inverse depth) and negative ξ dropped; subsample keeps 3 of 4
    assert s.size == 3 and np.all(np.isin(s, [2.0, 4.0, 2.0, 2.0]))


def test_robust_log_scale_ignores_outliers_and_reports_curvature():
    rng = np.random.default_rng(1)
    x = np.log(2.0) + 0.1 * rng.normal(size=40)
    bad = np.r_[x, np.log([20.0, 30.0, 0.01, 0.02])]  # 4 gross outliers (sky, wrong depth)
    mu, sig = robust_log_scale(np.exp(bad), sigma_log=0.1, huber_k=1.345)
    assert mu == pytest.approx(np.log(2.0), abs=0.05)
    assert np.mean(x) - 0.05 < mu < np.mean(x) + 0.05
    assert 0.1 / np.sqrt(44) < sig < 0.1 / np.sqrt(20)  # outliers add no curvature
    with pytest.raises(ValueError):
        robust_log_scale(np.array([]), 0.1, 1.345)


def test_gtsam_conversion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        S = sim3.exp(rng.normal(size=7))
        np.testing.assert_allclose(from_gtsam(to_gtsam(S)), S, atol=1e-10)
        p = rng.normal(size=3)
        np.testing.assert_allclose(to_gtsam(S).transformFrom(p), sim3.transform_points(S, p), atol=1e-10)


def _build(n: int, with_scale_factors: bool, drift: float = 0.02,
           mode: str = "per_keyframe") -> tuple[GlobalPoseGraph, SimulatedVO]:
    """Feed a drifting SimulatedVO straight into a graph (no corrections: VO units drift)."""
    cfg = GraphConfig(scale_factor_mode=mode, **FAST_DRIFT)
    T = circle_path(n, 60.0, turns=0.5)
    vo = SimulatedVO(T, drift_per_kf=drift, seed=3)
    src = SyntheticDepthSource(n, noise_log_sigma=0.05)
    graph = GlobalPoseGraph(cfg, anchor_scale=not with_scale_factors)
    from metricslam.depth.sample import sample_map

    prev = None
    for _ in range(n):
        kf = vo.next_keyframe()
        add_odometry_keyframe(graph, prev, kf, cfg)
        if with_scale_factors:
            z = sample_map(src.inv_depth_map(kf.image, kf.camera), kf.landmarks_uv_px,
                           (kf.camera.width_px, kf.camera.height_px))
            graph.add_scale_measurements(kf.kf_id, scale_measurements(kf.landmarks_inv_depth, z, cfg))
        graph.solve()
        prev = kf
    graph.solve(extra_iterations=5)
    return graph, vo


@pytest.mark.parametrize("mode", ["per_keyframe", "per_landmark"])
def test_scale_recovered_on_drifting_graph(mode):
    n = 60
    graph, vo = _build(n, with_scale_factors=True, mode=mode)
    est = graph.estimates()
    s_est = np.array([sim3.scale(est[k]) for k in range(n)])
    s_true = np.array(vo.sigma_at_kf)
    assert s_true[-1] / s_true[0] > 2.5  # the VO's units drifted a lot
    assert np.abs(s_est / s_true - 1).max() < 0.05
    p_err = np.linalg.norm(np.array([est[k][:3, 3] for k in range(n)]) - vo.T_true[:, :3, 3], axis=1)
    assert p_err.max() < 0.03 * 60 * np.pi / 2 + 0.5


def test_without_scale_factors_scale_drift_stays():
    n = 60
    graph, vo = _build(n, with_scale_factors=False)
    est = graph.estimates()
    s_est = np.array([sim3.scale(est[k]) for k in range(n)])
    np.testing.assert_allclose(s_est, 1.0, atol=1e-6)  # anchored at the first keyframe's units
    assert vo.sigma_at_kf[-1] > 2.5


def _null_space_dim(graph: GlobalPoseGraph) -> int:
    g = graph.factor_graph(include_anchor=False)
    A, _ = g.linearize(graph.values()).jacobian()
    eig = np.linalg.eigvalsh(A.T @ A)
    return int(np.sum(eig < 1e-9 * eig.max()))


@pytest.mark.parametrize("with_scale_factors,expected,mode", [
    (False, 7, "per_keyframe"), (True, 6, "per_keyframe"), (True, 6, "per_landmark")])
def test_gauge_freedom(with_scale_factors, expected, mode):
    graph, _ = _build(8, with_scale_factors=with_scale_factors, drift=0.01, mode=mode)
    assert _null_space_dim(graph) == expected


def test_range_gate_keeps_what_is_within_range_by_the_keyframes_own_scale():
    """Near landmarks measure the true scale, far ones read x0.5 too near (the network's
    far-range compression): the gate, iterating from the biased median, keeps exactly the near."""
    from metricslam.slam.graph.scale_factor import range_gate

    s_true = 2.0  # m per VO unit
    depth_m = np.concatenate([np.linspace(8, 35, 20), np.linspace(50, 100, 30)])
    xi = s_true / depth_m
    scales = np.where(depth_m <= 40, s_true, 0.5 * s_true)
    keep = range_gate(xi, scales, max_depth_m=40.0, min_keep=8)
    assert keep.tolist() == (depth_m <= 40).tolist()
    assert float(np.median(scales[keep])) == pytest.approx(s_true)
    # all far (and read right): the 8 nearest are kept, not none
    keep_far = range_gate(xi[20:], np.full(30, s_true), max_depth_m=40.0, min_keep=8)
    assert keep_far.sum() == 8 and keep_far[:8].all()
