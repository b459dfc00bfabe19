"""Pinhole camera (project/unproject/resize) and disparity <-> depth conversions."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from metricslam import disparity
from metricslam.camera import PinholeCamera
from metricslam.errors import CameraError

#: per-test settings (no global profile: other modules keep their own)
SETTINGS = settings(max_examples=40, deadline=None)

KITTI = PinholeCamera(fx_px=707.0912, fy_px=707.0912, cx_px=601.8873, cy_px=183.1104,
                      width_px=1226, height_px=370)
seeds = st.integers(0, 2**32 - 1)


@SETTINGS
@given(seeds)
def test_project_unproject_round_trip(seed):
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0, 0], [KITTI.width_px - 1, KITTI.height_px - 1], size=(50, 2))
    depth_m = rng.uniform(0.5, 80.0, size=50)
    p_cam = KITTI.unproject(uv, depth_m)
    assert np.allclose(p_cam[:, 2], depth_m)
    assert np.allclose(KITTI.project(p_cam), uv, atol=1e-9)


def test_principal_point_projects_from_the_optical_axis_and_behind_is_nan():
    uv = KITTI.project(np.array([[0.0, 0.0, 5.0], [1.0, 1.0, -2.0], [1.0, 1.0, 0.0]]))
    assert np.allclose(uv[0], [KITTI.cx_px, KITTI.cy_px])
    assert np.all(np.isnan(uv[1:]))
    assert not KITTI.in_image(uv[1:]).any()


def test_normalized_and_K():
    uv = np.array([[KITTI.cx_px + KITTI.fx_px, KITTI.cy_px - 2 * KITTI.fy_px]])
    assert np.allclose(KITTI.normalized(uv), [[1.0, -2.0]])
    K = KITTI.K
    assert np.allclose(PinholeCamera.from_K(K, 1226, 370).K, K)
    P = np.hstack([K, np.array([[-379.8], [0.0], [0.0]])])
    assert PinholeCamera.from_K(P, 1226, 370) == KITTI


@SETTINGS
@given(seeds, st.floats(0.2, 3.0), st.floats(0.2, 3.0))
def test_resize_maps_pixel_centres_consistently(seed, sx, sy):
    """A 3-D point projects to u in the original and (u + 0.5)·sx − 0.5 in the resized image."""
    rng = np.random.default_rng(seed)
    w2, h2 = max(1, round(KITTI.width_px * sx)), max(1, round(KITTI.height_px * sy))
    small = KITTI.resized(w2, h2)
    sx, sy = w2 / KITTI.width_px, h2 / KITTI.height_px
    p = np.column_stack([rng.uniform(-5, 5, 20), rng.uniform(-2, 2, 20), rng.uniform(1, 50, 20)])
    uv = KITTI.project(p)
    uv2 = small.project(p)
    assert np.allclose(uv2[:, 0], (uv[:, 0] + 0.5) * sx - 0.5)
    assert np.allclose(uv2[:, 1], (uv[:, 1] + 0.5) * sy - 0.5)
    back = small.resized(KITTI.width_px, KITTI.height_px)
    for name in ("fx_px", "fy_px", "cx_px", "cy_px"):
        assert getattr(back, name) == pytest.approx(getattr(KITTI, name))


def test_in_image_edges():
    cam = PinholeCamera(fx_px=100, fy_px=100, cx_px=1.5, cy_px=1.5, width_px=4, height_px=4)
    uv = np.array([[-0.5, -0.5], [3.5, 3.5], [-0.51, 0.0], [0.0, 3.51], [1.0, 1.0]])
    assert cam.in_image(uv).tolist() == [True, True, False, False, True]
    assert cam.in_image(uv, margin_px=1.0).tolist() == [False, False, False, False, True]


def test_camera_is_frozen_and_validates():
    with pytest.raises(ValidationError, match="frozen"):
        KITTI.fx_px = 1.0  # type: ignore[misc]
    with pytest.raises(ValidationError, match="fx_px"):
        PinholeCamera(fx_px=-1, fy_px=1, cx_px=0, cy_px=0, width_px=10, height_px=10)
    with pytest.raises(CameraError):
        PinholeCamera.from_K(np.eye(2), 10, 10)
    with pytest.raises(CameraError):
        PinholeCamera.from_K(np.diag([0.0, 1.0, 1.0]), 10, 10)


# ---------------------------------------------------------------- disparity

@SETTINGS
@given(seeds)
def test_disparity_depth_round_trip(seed):
    rng = np.random.default_rng(seed)
    depth_m = rng.uniform(0.5, 200.0, size=(8, 16))
    d = disparity.disparity_from_depth(depth_m, 707.0912, 0.54)
    assert np.allclose(disparity.depth_from_disparity(d, 707.0912, 0.54), depth_m)
    inv = disparity.inv_depth_from_disparity(d, 707.0912, 0.54)
    assert np.allclose(inv, 1.0 / depth_m)


def test_disparity_edge_values_never_raise():
    d = np.array([0.0, -1.0, np.nan, np.inf, 10.0])
    z = disparity.depth_from_disparity(d, 700.0, 0.5)
    assert np.isinf(z[:4]).all() and z[4] == pytest.approx(35.0)
    assert disparity.inv_depth_from_disparity(d, 700.0, 0.5)[:3].tolist() == [0.0, 0.0, 0.0]
    assert disparity.disparity_from_depth(np.array([0.0, np.inf, np.nan]), 700.0, 0.5).tolist() == [0, 0, 0]


def test_width_fraction_matches_pixel_disparity():
    """The network's disparity fraction scales with the caller's image width."""
    d_frac = np.array([0.01, 0.05])
    inv = disparity.inv_depth_from_width_fraction(d_frac, fx_px=707.0, width_px=1226, baseline_m=0.54)
    assert np.allclose(inv, d_frac * 1226 / (707.0 * 0.54))
    # same scene at half resolution: fx and width halve, metric inverse depth is unchanged
    inv_half = disparity.inv_depth_from_width_fraction(d_frac, fx_px=353.5, width_px=613, baseline_m=0.54)
    assert np.allclose(inv, inv_half)


@pytest.mark.parametrize("fx, b", [(0.0, 0.5), (700.0, 0.0), (np.nan, 0.5), (700.0, -1.0)])
def test_disparity_rejects_bad_camera(fx, b):
    with pytest.raises(CameraError):
        disparity.depth_from_disparity(np.ones(2), fx, b)
    with pytest.raises(CameraError):
        disparity.disparity_from_depth(np.ones(2), fx, b)


def test_width_fraction_rejects_zero_width():
    with pytest.raises(CameraError):
        disparity.inv_depth_from_width_fraction(np.ones(2), 700.0, 0.0, 0.5)
