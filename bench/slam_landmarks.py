"""Where a SLAM run puts its scale landmarks: the metric depth the SLAM itself gives them.

Runs the system of ``metricslam run --deterministic`` in-process (the one session builder) and,
for every keyframe the back end receives, keeps the landmarks it turns into scale measurements
(VO inverse depth ``ξ_j > 0``, network inverse depth within the graph's usable range) with the
depth the SLAM estimates for them, ``s_kf / ξ_j`` (``s_kf``: the keyframe's final optimized
Sim(3) scale).
"""

from __future__ import annotations

import numpy as np

from metricslam.depth import DepthModel, sample_map
from metricslam.geometry.sim3 import scale as sim3_scale
from metricslam.slam.session_builder import build_session
from metricslam.slam.system_config import SystemConfig


class _ModelSource:
    """The network as the back end's depth source (what ``metricslam run`` uses, from a loaded model)."""

    def __init__(self, model: DepthModel) -> None:
        self.model = model

    def inv_depth_map(self, image: np.ndarray, camera) -> np.ndarray:
        return self.model.predict_inv_depth(image, camera=camera).inv_depth_per_m


def scale_landmark_depths(seq, model: DepthModel, preset: str) -> dict:
    """``{"preset", "keyframes", "keyframes_used", "depths_m"}``: ``depths_m`` (N,) metres, pooled
    over keyframes. The network map of a keyframe is recomputed from its image (deterministic,
    the same map the back end got) rather than matched to the back end's request."""
    config = SystemConfig(vo={"preset": preset}, deterministic=True)
    graph_cfg = config.graph_config()
    source = _ModelSource(model)
    pipe = build_session(seq.camera, config, depth_source=source)
    backend = pipe.backend
    keyframes = []
    forward = backend.on_keyframe_marginalized

    def record(kf):
        keyframes.append(kf)
        return forward(kf)

    backend.on_keyframe_marginalized = record
    try:
        for i in range(len(seq)):
            pipe.process(seq[i])
    finally:
        pipe.close()
    S_by_frame = backend.optimized_keyframe_poses()
    depths = []
    for kf in keyframes:
        S = S_by_frame.get(kf.frame_index)
        xi = np.asarray(kf.landmarks_inv_depth, float).reshape(-1)
        if S is None or xi.size == 0:
            continue
        inv_map = source.inv_depth_map(kf.image, seq.camera)
        z_net_inv = sample_map(inv_map, kf.landmarks_uv_px, (kf.image.shape[1], kf.image.shape[0]))
        ok = (np.isfinite(xi) & (xi > 0) & np.isfinite(z_net_inv) & (z_net_inv >= graph_cfg.min_inv_depth_per_m)
              & (z_net_inv <= graph_cfg.max_inv_depth_per_m))
        depths.append(sim3_scale(np.asarray(S, float)) / xi[ok])
    return {"preset": preset, "keyframes": len(keyframes), "keyframes_used": len(depths),
            "depths_m": np.concatenate(depths) if depths else np.zeros(0)}
