"""A verified relocalization match is refined on the corners of the map keyframes around it
(``Relocalizer._refined``): a pose verified against one map keyframe, decimetres off, lands on
the true one when the neighbours' corners see the same scene; with too few correspondences the
match is kept as verified."""

from __future__ import annotations

import numpy as np
from metricslam.camera import PinholeCamera
from metricslam.geometry import se3, sim3, so3
from metricslam.slam.graph.config import LoopConfig
from metricslam.slam.loop.corners import CornerFeatures
from metricslam.slam.map.relocalizer import Relocalizer

CAMERA = PinholeCamera(fx_px=700.0, fy_px=700.0, cx_px=600.0, cy_px=180.0, width_px=1200, height_px=360)
RNG = np.random.default_rng(7)


def _scene(n: int) -> np.ndarray:
    """World points (n, 3) in front of cameras looking down +z near the origin."""
    return np.c_[RNG.uniform(-15, 15, n), RNG.uniform(-3, 2, n), RNG.uniform(20, 60, n)]


def _setup(n_per_kf: int):
    T_map_kf = {10 + k: se3.from_rt(so3.exp(np.array([0.0, 0.02 * k, 0.0])), np.array([0.2 * k, 0.0, 2.0 * k]))
                for k in range(5)}
    world = [_scene(n_per_kf) for _ in T_map_kf]
    desc = [RNG.integers(0, 256, (n_per_kf, 32), dtype=np.uint8) for _ in T_map_kf]
    r = Relocalizer.__new__(Relocalizer)  # no saved map file needed for the refinement
    r.config, r._ids, r._T_map_kf = LoopConfig(), np.array(sorted(T_map_kf)), T_map_kf
    r._features = []
    for T, p_w, d in zip(T_map_kf.values(), world, desc):
        p_kf = (p_w - T[:3, 3]) @ T[:3, :3]
        r._features.append(CornerFeatures(CAMERA.project(p_kf), d, p_kf))
    T_map_query = se3.from_rt(so3.exp(np.array([0.0, 0.03, 0.0])), np.array([0.3, 0.0, 3.0]))
    p_w, d = np.vstack(world), np.vstack(desc)
    p_q = (p_w - T_map_query[:3, 3]) @ T_map_query[:3, :3]
    new = CornerFeatures(CAMERA.project(p_q), d, np.full((len(d), 3), np.nan))
    return r, new, T_map_query


def test_a_verified_match_decimetres_off_is_refined_onto_the_local_map():
    r, new, T_map_query = _setup(60)
    T_kf_query = np.linalg.inv(r._T_map_kf[12]) @ T_map_query  # matched to row 2 (map keyframe 12)
    off = T_kf_query @ se3.from_rt(so3.exp(np.array([0.0, 0.002, 0.001])), np.array([0.25, 0.0, -0.4]))
    S = r._refined(new, 2, sim3.from_se3(off, 1.7), CAMERA)
    np.testing.assert_allclose(sim3.split(S)[1], T_kf_query[:3, 3], atol=1e-3)
    assert np.isclose(sim3.scale(S), 1.7)  # the scale is the match's own


def test_too_few_correspondences_keep_the_match_as_verified():
    r, new, T_map_query = _setup(2)  # 2 corners a keyframe, 10 in all: below the minimum
    off = sim3.from_se3(np.linalg.inv(r._T_map_kf[12]) @ T_map_query @ se3.from_rt(np.eye(3), np.array([0.5, 0, 0])))
    np.testing.assert_array_equal(r._refined(new, 2, off, CAMERA), off)
