"""All-corner loop verification on rendered frames (``metricslam.slam.loop.corners``).

Rendered depth stands in for the network's map, and each keyframe gets its own VO units
(metres per unit ``m_k``), so the verified ``S_old_new`` must carry the unit ratio
``m_new / m_old`` and the ground-truth motion in the old keyframe's units. A different place
must not verify; triangulation against the previous keyframe (the ``--no-scale`` path) must
reproduce the rendered depth in keyframe units.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from metricslam.geometry import se3, sim3
from metricslam.slam.graph.config import LoopConfig
from metricslam.slam.loop import corners as C

OLD, NEW, ELSEWHERE = 7, 133, 70
M_OLD, M_NEW = 2.0, 0.5  # metres per VO unit of each keyframe


@pytest.fixture(scope="module")
def scene():
    from metricslam.synth.scene import SynthConfig, SynthScene

    return SynthScene.procedural(150, 3, "loop", SynthConfig(width_px=620, height_px=188))


def _features(scene, index: int, m_per_unit: float) -> C.CornerFeatures:
    f = scene.frame(index)
    with np.errstate(divide="ignore"):
        inv_map = np.where(f.depth_m > 0, 1.0 / f.depth_m, np.nan).astype(np.float32)
    lm = cv2.goodFeaturesToTrack(f.left, 60, 0.01, 10).reshape(-1, 2).astype(float)
    d = f.depth_m[lm[:, 1].round().astype(int), lm[:, 0].round().astype(int)]
    lm_xi = np.where(d > 0, m_per_unit / np.maximum(d, 1e-6), np.nan)  # ξ in keyframe units
    uv, desc = C.detect_corners(cv2.ORB_create(nfeatures=1000, nlevels=4, fastThreshold=12), f.left)
    from metricslam.depth.sample import sample_map

    size = (scene.camera.width_px, scene.camera.height_px)
    m_hat = C.metres_per_unit(lm_xi, sample_map(inv_map, lm, size))
    assert m_hat == pytest.approx(m_per_unit, rel=0.02)
    return C.CornerFeatures(uv, desc, C.network_points(uv, sample_map(inv_map, uv, size), m_hat, scene.camera))


def test_revisit_verifies_with_unit_ratio(scene):
    old, new = _features(scene, OLD, M_OLD), _features(scene, NEW, M_NEW)
    res = C.verify_corners(new, old, scene.camera, LoopConfig(), np.random.default_rng(0))
    assert res is not None and res.n_inliers >= 30
    T = se3.inverse(scene.T_world_cam[OLD]) @ scene.T_world_cam[NEW]
    R, t, s = sim3.split(res.S_old_new)
    assert s == pytest.approx(M_NEW / M_OLD, rel=0.05)
    assert np.linalg.norm(t * M_OLD - T[:3, 3]) < 0.3  # metres
    assert np.degrees(np.linalg.norm(cv2.Rodrigues(R.T @ T[:3, :3])[0])) < 0.5


def test_other_place_does_not_verify(scene):
    old, other = _features(scene, OLD, M_OLD), _features(scene, ELSEWHERE, M_NEW)
    assert C.verify_corners(other, old, scene.camera, LoopConfig(), np.random.default_rng(0)) is None


def test_triangulation_matches_rendered_depth(scene):
    prev_i, k = 40, 42
    orb = cv2.ORB_create(nfeatures=1000, nlevels=4, fastThreshold=12)
    fp, fk = scene.frame(prev_i), scene.frame(k)
    uv_p, d_p = C.detect_corners(orb, fp.left)
    uv_k, d_k = C.detect_corners(orb, fk.left)
    T_prev_k = se3.inverse(scene.T_world_cam[prev_i]) @ scene.T_world_cam[k]
    T_units = T_prev_k.copy()
    T_units[:3, 3] /= M_NEW  # the VO's T_prevkf_kf is in keyframe units
    pts = C.triangulated_points(uv_k, d_k, uv_p, d_p, T_units, scene.camera)
    ok = np.isfinite(pts).all(axis=1)
    assert ok.sum() >= 50
    d_true = fk.depth_m[uv_k[ok, 1].round().astype(int), uv_k[ok, 0].round().astype(int)]
    good = d_true > 0
    rel = np.abs(pts[ok, 2][good] * M_NEW - d_true[good]) / d_true[good]
    assert np.median(rel) < 0.05


def _geo_features(scene, index: int, m_per_unit: float, gamma: float) -> C.CornerFeatures:
    """Corners with "network" depth distorted as ``z_net ∝ z^gamma`` (verification) and depth
    triangulated against frame ``index - 2`` with the true motion in keyframe units."""
    from metricslam.depth.sample import sample_map

    f, fp = scene.frame(index), scene.frame(index - 2)
    with np.errstate(divide="ignore"):
        inv = np.where(f.depth_m > 0, 1.0 / f.depth_m, np.nan)
    inv_net = ((10.0 * inv) ** gamma / 10.0).astype(np.float32)
    lm = cv2.goodFeaturesToTrack(f.left, 60, 0.01, 10).reshape(-1, 2).astype(float)
    d = f.depth_m[lm[:, 1].round().astype(int), lm[:, 0].round().astype(int)]
    lm_xi = np.where(d > 0, m_per_unit / np.maximum(d, 1e-6), np.nan)
    orb = cv2.ORB_create(nfeatures=1000, nlevels=4, fastThreshold=12)
    uv, desc = C.detect_corners(orb, f.left)
    uv_p, desc_p = C.detect_corners(orb, fp.left)
    size = (scene.camera.width_px, scene.camera.height_px)
    m_hat = C.metres_per_unit(lm_xi, sample_map(inv_net, lm, size))
    pts = C.network_points(uv, sample_map(inv_net, uv, size), m_hat, scene.camera)
    T_prev_k = se3.inverse(scene.T_world_cam[index - 2]) @ scene.T_world_cam[index]
    T_prev_k[:3, 3] /= m_per_unit
    tri = C.triangulated_points(uv, desc, uv_p, desc_p, T_prev_k, scene.camera)
    return C.CornerFeatures(uv, desc, pts, tri)


def test_geometric_measurement_does_not_use_network_depth(scene):
    """Network depth distorted differently in the two images moves the network-measured loop
    (0.2 m here); the geometric one (translation and scale from triangulated corners) does not."""
    old, new = _geo_features(scene, OLD, M_OLD, 0.8), _geo_features(scene, NEW, M_NEW, 1.0)
    T = se3.inverse(scene.T_world_cam[OLD]) @ scene.T_world_cam[NEW]
    errs = {}
    for meas in ("network", "geometric"):
        res = C.verify_corners(new, old, scene.camera, LoopConfig(measurement=meas), np.random.default_rng(0))
        assert res is not None
        _, t, s = sim3.split(res.S_old_new)
        errs[meas] = (s / (M_NEW / M_OLD), np.linalg.norm(t * M_OLD - T[:3, 3]), res.sigmas)
    s_geo, t_geo, sig = errs["geometric"]
    assert s_geo == pytest.approx(1.0, abs=max(0.05, 2 * sig[6]))
    assert t_geo < 0.1 < errs["network"][1]
    assert sig is not None and np.all(sig > 0) and errs["network"][2] is None
