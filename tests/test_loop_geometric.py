"""Loop translation and scale from triangulated corners only (``metricslam.slam.loop.geometric_sim3``).

Two keyframes see one scene; each keyframe's points are in its own VO units (metres per unit
``m_old``, ``m_new``) with 1 % noise per point and 1.5 % per keyframe, the new image's pixels 0.5 px noise. The
measured ``S_old_new`` must carry the unit ratio ``m_new / m_old`` and the true motion whatever
the (network-based) starting guess, and its sigmas must be honest (normalized errors ~ N(0, 1)).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from metricslam.geometry import se3, sim3, so3
from metricslam.slam.graph.synthetic import CAMERA
from metricslam.slam.loop.geometric_sim3 import UNIT_SIGMA_LOG, measure_loop


def _scene(seed: int, m_old: float, m_new: float, t_m: np.ndarray, n: int = 60, outliers: int = 10,
           unit_sigma: float = UNIT_SIGMA_LOG):
    rng = np.random.default_rng(seed)
    uv = np.column_stack([rng.uniform(20, CAMERA.width_px - 20, n), rng.uniform(10, CAMERA.height_px - 10, n)])
    P_old_m = CAMERA.unproject(uv, rng.uniform(4.0, 30.0, n))  # metric, old camera frame
    T_old_new = se3.from_rt(so3.exp(np.radians([0.5, 4.0, -0.3])), t_m)
    P_new_m = (se3.inverse(T_old_new)[:3, :3] @ P_old_m.T).T + se3.inverse(T_old_new)[:3, 3]
    uv_new = CAMERA.project(P_new_m) + 0.5 * rng.normal(size=(n, 2))
    # per-point depth noise 1 %, and each keyframe's triangulated units off by UNIT_SIGMA_LOG
    # (measured spread of triangulated vs true units on the rendered loop)
    u_old, u_new = np.exp(unit_sigma * rng.normal(size=2))
    p_old = P_old_m / m_old * u_old * np.exp(0.01 * rng.normal(size=(n, 1)))
    p_new = P_new_m / m_new * u_new * np.exp(0.01 * rng.normal(size=(n, 1)))
    p_new[rng.random(n) < 0.4] = np.nan  # not every corner is triangulated on both sides
    uv_new[:outliers] = rng.uniform(0, CAMERA.width_px, (outliers, 2))  # wrong matches
    return T_old_new, uv_new, p_old, p_new


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), log_ratio=st.floats(-1.0, 1.0), guess_bias=st.floats(0.7, 1.4))
def test_unit_ratio_and_motion_whatever_the_guess(seed, log_ratio, guess_bias):
    m_old = 2.0
    m_new = m_old * float(np.exp(log_ratio))
    T, uv_new, p_old, p_new = _scene(seed, m_old, m_new, np.array([1.5, 0.1, 3.0]), unit_sigma=0.0)
    guess = T[:3, 3] / m_old * guess_bias  # e.g. the network's units, off by guess_bias
    res = measure_loop(T[:3, :3], guess, uv_new, p_old, p_new, CAMERA, sigma_rot_rad=0.01)
    assert res is not None
    _, t, s = sim3.split(res.S_old_new)
    assert s == pytest.approx(m_new / m_old, rel=0.05)
    assert np.linalg.norm(t * m_old - T[:3, 3]) < 0.15
    assert res.n_scale >= 5 and res.n_translation >= 6


def test_sigmas_are_honest():
    """Normalized errors of log-scale and translation over many draws: mean square ~ 1, not 100."""
    z_s, z_t = [], []
    for seed in range(60):
        T, uv_new, p_old, p_new = _scene(seed, 1.0, 1.3, np.array([0.5, 0.0, 2.0]))
        res = measure_loop(T[:3, :3], T[:3, 3], uv_new, p_old, p_new, CAMERA, sigma_rot_rad=0.01)
        _, t, s = sim3.split(res.S_old_new)
        z_s.append((np.log(s) - np.log(1.3)) / res.sigmas[6])
        u = T[:3, :3].T @ (t - T[:3, 3]) / s  # tangent translation error, new units
        z_t.extend(u / res.sigmas[3:6])
    assert 0.1 < np.mean(np.square(z_s)) < 3.0
    assert 0.05 < np.mean(np.square(z_t)) < 3.0


def test_too_few_triangulated_corners_give_no_measurement():
    T, uv_new, p_old, p_new = _scene(3, 1.0, 1.0, np.array([0.5, 0.0, 2.0]))
    p_old[5:] = np.nan
    assert measure_loop(T[:3, :3], T[:3, 3], uv_new, p_old, p_new, CAMERA, sigma_rot_rad=0.01) is None
