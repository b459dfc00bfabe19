"""Ground landmarks: the road plane found from VO geometry alone, and scale factors from it."""

from __future__ import annotations

import numpy as np
import pytest
from metricslam.camera import PinholeCamera
from metricslam.geometry import sim3
from metricslam.slam.graph.backend import GlobalBackend
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.ground import ground_landmarks
from metricslam.slam.types import MarginalizedKeyframe

CAM = PinholeCamera(fx_px=100.0, fy_px=100.0, cx_px=32.0, cy_px=16.0, width_px=64, height_px=32)
HEIGHT_VO = 1.0  # the road lies 1 VO unit below the camera
TRUE_SCALE_M = 1.65  # metres per VO unit


def _scene(seed: int = 0, tilt_rad: float = 0.0):
    """(uv (M,2), ξ (M,), on_road (M,)): 30 road landmarks below the horizon and 20 on objects
    standing on the road (nearer than the road behind them) or above the horizon."""
    rng = np.random.default_rng(seed)
    u_road = rng.uniform(2, 62, 30)
    v_road = rng.uniform(19, 31, 30)
    # road plane n·X = h with n = (0, cos, sin)·: tilt about the x axis
    n = np.array([0.0, np.cos(tilt_rad), np.sin(tilt_rad)])
    rays = CAM.unproject(np.column_stack([u_road, v_road]), 1.0)
    z_road = HEIGHT_VO / (rays @ n)
    u_obj = rng.uniform(2, 62, 20)
    v_obj = np.r_[rng.uniform(2, 15, 10), rng.uniform(19, 31, 10)]
    z_obj = rng.uniform(2.0, 5.0, 20)
    uv = np.r_[np.column_stack([u_road, v_road]), np.column_stack([u_obj, v_obj])]
    xi = np.r_[1.0 / z_road, 1.0 / z_obj]
    return uv, xi, np.r_[np.ones(30, bool), np.zeros(20, bool)]


def test_finds_the_road_landmarks_whatever_the_vo_scale():
    uv, xi, on_road = _scene()
    mask = ground_landmarks(uv, xi, CAM)
    assert mask[on_road].mean() > 0.95 and not mask[~on_road].any()
    # the VO's unit is arbitrary: a 7x different scale finds the same landmarks
    np.testing.assert_array_equal(ground_landmarks(uv, xi / 7.0, CAM), mask)
    np.testing.assert_array_equal(ground_landmarks(uv, xi, CAM), mask)  # seeded: deterministic


def test_no_road_in_view_gives_no_ground():
    uv, xi, on_road = _scene()
    assert not ground_landmarks(uv[~on_road], xi[~on_road], CAM).any()
    assert not ground_landmarks(uv[:5], xi[:5], CAM).any()  # too few landmarks for a plane


def test_a_steep_plane_is_not_ground():
    uv, xi, _ = _scene(tilt_rad=np.radians(10))
    assert ground_landmarks(uv, xi, CAM, max_tilt_deg=25).sum() >= 28
    uv, xi, _ = _scene(tilt_rad=np.radians(40))  # a wall-like slope, not a road
    assert not ground_landmarks(uv, xi, CAM, max_tilt_deg=25).any()


class _RoadDepth:
    """A depth source that knows only the road: every pixel below the horizon gets the road's
    metric inverse depth, so landmarks on objects get a wrong (too far) value there."""

    def inv_depth_map(self, image: np.ndarray, camera: PinholeCamera) -> np.ndarray:
        v = np.arange(camera.height_px, dtype=np.float32)[:, None]  # cell i is centred on row i
        road = np.clip((v - camera.cy_px) / (camera.fy_px * HEIGHT_VO * TRUE_SCALE_M), 1.0 / 60, None)
        return np.repeat(road, camera.width_px, axis=1).astype(np.float32)


@pytest.mark.parametrize("mode, exact", [("ground", True), ("all", False)])
def test_ground_mode_takes_the_scale_from_the_road_only(mode, exact):
    uv, xi, _ = _scene()
    kf = MarginalizedKeyframe(kf_id=0, frame_index=0, t_ns=0, segment_id=0, T_vo_kf=np.eye(4),
                              T_prevkf_kf=None, landmarks_uv_px=uv, landmarks_inv_depth=xi,
                              image=np.zeros((32, 64), np.uint8), camera=CAM)
    backend = GlobalBackend(GraphConfig(inline=True, scale_landmarks=mode, loop={"enabled": False}),
                            depth_source=_RoadDepth())
    backend.on_keyframe_marginalized(kf)
    scale = sim3.scale(backend.optimized_keyframe_poses()[0])
    stats = backend.stats()
    backend.close()
    if exact:
        assert scale == pytest.approx(TRUE_SCALE_M, rel=0.02)
        assert stats["ground_keyframes"] == 1 and stats["ground_fallbacks"] == 0
    else:  # the objects pull the paper's all-landmark estimate off
        assert scale > 1.1 * TRUE_SCALE_M
        assert stats["ground_keyframes"] == 0
