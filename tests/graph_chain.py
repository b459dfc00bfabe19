"""Test helper: feed simulated VO keyframes into a :class:`GlobalPoseGraph` as an odometry chain."""

from __future__ import annotations

from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.odometry import odometry_information, relative_sim3
from metricslam.slam.graph.sim3_graph import GlobalPoseGraph
from metricslam.slam.types import MarginalizedKeyframe

#: Graph noise for tests whose simulated VO drifts in scale by 1-2 % per keyframe, on purpose
#: several times the measured VO's random walk (0.006 per keyframe, the default
#: ``odom_sigma_log_scale``); a graph configured for that VO rightly refuses to follow such drift.
FAST_DRIFT = {"odom_sigma_log_scale": 0.03, "scale_sigma_floor_log": 0.06}


def add_odometry_keyframe(graph: GlobalPoseGraph, prev: MarginalizedKeyframe | None,
                          kf: MarginalizedKeyframe, cfg: GraphConfig) -> None:
    """Insert ``kf``: the first keyframe at its VO pose, later ones chained to ``prev`` by the
    relative Sim(3) of their VO poses (initial guess = prev's estimate ∘ that relative pose)."""
    if prev is None:
        graph.add_keyframe(kf.kf_id, kf.T_vo_kf)
        return
    S_rel = relative_sim3(prev.T_vo_kf, kf.T_vo_kf)
    graph.add_keyframe(kf.kf_id, graph.estimate(prev.kf_id) @ S_rel, prev.kf_id, S_rel,
                       odometry_information(S_rel, None, cfg))


def run_backend(backend, vo, n: int) -> list:
    """Hand ``n`` keyframes of the simulated ``vo`` to ``backend`` one by one, warping the VO by
    each correction as the pipeline does, then close the backend. Returns the corrections applied
    ((4, 4) Sim(3) each, in order)."""
    applied = []
    for _ in range(n):
        backend.on_keyframe_marginalized(vo.next_keyframe())
        S = backend.take_correction()
        if S is not None:
            applied.append(S)
            vo.apply_similarity(S)
    backend.close()
    return applied
