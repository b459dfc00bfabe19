"""Loops injected through the back end's loop-detector interface, measured like the geometric
verifier reports them (relative Sim(3) in VO units + its own sigmas): a true loop removes the
drift of a scale-drifting circle without disturbing the learned metric scale; a false one is
refused."""

from __future__ import annotations

import numpy as np
from graph_chain import run_backend
from metricslam.geometry import sim3
from metricslam.slam.graph.backend import GlobalBackend
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.synthetic import (
    SimulatedVO,
    SyntheticDepthSource,
    circle_path,
)
from metricslam.slam.loop import LoopCandidate

N = 80
SIGMAS = np.array([0.01] * 3 + [0.05] * 3 + [0.03])  # what the geometric verifier reports


class _InjectingDetector:
    """Stands in for ``LoopDetector``: at keyframe ``at`` reports a loop to ``old``."""

    def __init__(self, vo: SimulatedVO, T_true: np.ndarray, old: int, at: int, claimed_new: int) -> None:
        self.vo, self.T, self.old, self.at, self.claimed_new = vo, T_true, old, at, claimed_new

    def add_and_query(self, kf_id, image, camera, uv, xi, inv_depth_map=None, T_prevkf_kf=None):
        if kf_id != self.at:
            return []
        # truth in VO units: S_world_kf = (R, t, metres per unit of that keyframe)
        S = [sim3.from_se3(self.T[k], self.vo.sigma_at_kf[k]) for k in (self.old, self.claimed_new)]
        return [LoopCandidate(self.old, kf_id, sim3.inverse(S[0]) @ S[1], 200, 1.0, SIGMAS)]

    store_counters: dict = {}

    def close(self) -> None:
        pass


def _run(detector_args: tuple | None, seed: int = 3):
    T = circle_path(N, 40.0, turns=(N - 1) / N)  # the last keyframe is next to the first
    vo = SimulatedVO(T, drift_per_kf=0.01, drift_noise=0.03, seed=seed)  # ~0.2 deg rotation noise per step
    det = None if detector_args is None else _InjectingDetector(vo, T, *detector_args)
    backend = GlobalBackend(GraphConfig(inline=True), depth_source=SyntheticDepthSource(N, bias=1.0),
                            loop_detector=det)
    run_backend(backend, vo, N)
    est = backend.optimized_keyframe_poses()
    p_err = np.linalg.norm(np.array([est[k][:3, 3] for k in range(N)]) - T[:, :3, 3], axis=1)
    s_err = np.array([sim3.scale(est[k]) for k in range(N)]) / np.array(vo.sigma_at_kf) - 1
    return backend, p_err, s_err


def test_injected_true_loop_removes_drift_and_keeps_metric_scale():
    _, p0, s0 = _run(None)
    backend, p1, s1 = _run((0, N - 1, N - 1))
    assert len(backend.loops) == 1
    assert p0[-1] > 2.0  # drift without the loop
    assert p1[-1] < 0.3 * p0[-1]
    assert np.abs(s1).max() < max(0.04, 1.2 * np.abs(s0).max())  # metric scale untouched


def test_injected_false_loop_is_refused():
    # "the newest keyframe is where keyframe 40 was": 80 m across the circle from the truth
    backend, p1, _ = _run((0, N - 1, N // 2))
    assert backend.loops == []
    assert backend.stats()["loops_rejected"] == 1
    _, p0, _ = _run(None)
    np.testing.assert_allclose(p1, p0, atol=1e-6)
