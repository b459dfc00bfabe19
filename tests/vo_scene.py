"""Seeded synthetic window for the VO tests: keyframes moving forward past a point cloud.

``make_window(seed)`` returns a :class:`WindowProblem` with exact (noise-free, or with pixel
noise) observations, together with the true poses and inverse depths.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.geometry import se3
from metricslam.slam.vo.linear_system import WindowProblem

CAMERA = PinholeCamera(fx_px=500.0, fy_px=500.0, cx_px=319.5, cy_px=239.5, width_px=640, height_px=480)


@dataclass
class SyntheticWindow:
    problem: WindowProblem  # true values
    T_world_kf_true: np.ndarray
    rho_true: np.ndarray


def make_window(seed: int = 0, n_kf: int = 5, n_per_kf: int = 40, noise_px: float = 0.0,
                step_m: float = 0.5) -> SyntheticWindow:
    rng = np.random.default_rng(seed)
    K = CAMERA.K
    poses = []
    for i in range(n_kf):
        omega = rng.normal(0, 0.02, 3)
        t = np.array([0.1 * np.sin(i), 0.05 * rng.normal(), step_m * i])
        poses.append(se3.from_rt(se3.exp(np.r_[omega, 0, 0, 0])[:3, :3], t))
    poses = np.array(poses)
    lm_host, lm_bearing, lm_rho, obs_lm, obs_kf, obs_uv = [], [], [], [], [], []
    for h in range(n_kf):
        uv = np.stack([rng.uniform(20, 620, n_per_kf), rng.uniform(20, 460, n_per_kf)], axis=1)
        depth = rng.uniform(3.0, 30.0, n_per_kf)
        p_h = CAMERA.unproject(uv, depth)
        p_w = se3.transform_points(poses[h], p_h)
        for j in range(n_per_kf):
            idx = len(lm_rho)
            seen = False
            for t in range(n_kf):
                if t == h:
                    continue
                p_t = se3.transform_points(se3.inverse(poses[t]), p_w[j])
                if p_t[2] <= 0.1:
                    continue
                uv_t = CAMERA.project(p_t[None])[0]
                if not CAMERA.in_image(uv_t):
                    continue
                obs_lm.append(idx)
                obs_kf.append(t)
                obs_uv.append(uv_t + rng.normal(0, noise_px, 2) if noise_px > 0 else uv_t)
                seen = True
            if seen:
                lm_host.append(h)
                lm_bearing.append(np.r_[(uv[j] - K[:2, 2]) / np.diag(K)[:2], 1.0])
                lm_rho.append(1.0 / depth[j])
            else:  # drop the observations of this landmark (none were added)
                pass
    problem = WindowProblem(
        T_world_kf=poses, lm_host=np.array(lm_host), lm_bearing=np.array(lm_bearing),
        lm_rho=np.array(lm_rho), obs_lm=np.array(obs_lm), obs_kf=np.array(obs_kf),
        obs_uv_px=np.array(obs_uv), K=K)
    return SyntheticWindow(problem, poses.copy(), np.array(lm_rho))
