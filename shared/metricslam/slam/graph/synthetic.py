"""Seeded synthetic keyframe streams for testing and benchmarking the global graph.

:class:`SimulatedVO` plays the local VO: it integrates the true relative motion with a drifting
scale (metres per VO unit ``σ_k`` performs a random walk with a bias), marginalizes every
keyframe at once, and applies the back end's corrections to its own frame and units exactly as
the real VO's ``apply_similarity`` must (``T_vo ← S·T_vo`` made rigid, ``σ ← σ / scale(S)``).
The scene's metric inverse depth is linear in the pixel (``z = a + b·u/W + c·v/H``), so a
coarse map sampled bilinearly reproduces it; :class:`SyntheticDepthSource` returns such maps
with multiplicative per-cell noise.
"""

from __future__ import annotations

import hashlib

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.geometry import se3, sim3
from metricslam.slam.types import MarginalizedKeyframe

CAMERA = PinholeCamera(fx_px=500.0, fy_px=500.0, cx_px=319.5, cy_px=95.5, width_px=640, height_px=192)


def circle_path(n: int, radius_m: float = 50.0, turns: float = 1.0) -> np.ndarray:
    """(n, 4, 4) camera poses ``T_world_cam`` driving a horizontal circle (y down), first at I."""
    T = np.empty((n, 4, 4))
    for i in range(n):
        a = 2 * np.pi * turns * i / n
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        p = np.array([radius_m * (1 - np.cos(a)), 0.0, radius_m * np.sin(a)])
        T[i] = se3.from_rt(R, p)
    T0_inv = se3.inverse(T[0])
    return np.einsum("ij,njk->nik", T0_inv, T)


def inv_depth_plane(image_key: int) -> tuple[float, float, float]:
    """Per-keyframe coefficients ``(a, b, c)`` of ``z(u, v) = a + b·u/W + c·v/H`` (1/m)."""
    rng = np.random.default_rng(image_key)
    return 1.0 / 40.0 + 0.01 * rng.random(), 0.02 * rng.random(), 0.12 + 0.05 * rng.random()


class SimulatedVO:
    """Produces :class:`MarginalizedKeyframe` s along ``T_world_kf_true`` with drifting scale.

    Args:
        T_world_kf_true: (N, 4, 4) true metric keyframe poses.
        drift_per_kf: mean of ``log σ_k − log σ_{k−1}`` (scale drift per keyframe).
        drift_noise: std of that step, plus rotation/translation noise scale.
        sigma0: initial metres per VO unit.
        seed: RNG seed.
        n_landmarks: landmarks per keyframe.
    """

    def __init__(self, T_world_kf_true: np.ndarray, drift_per_kf: float = 0.01, drift_noise: float = 0.002,
                 sigma0: float = 1.0, seed: int = 0, n_landmarks: int = 60,
                 camera: PinholeCamera = CAMERA) -> None:
        self.T_true = np.asarray(T_world_kf_true, dtype=float)
        self.rng = np.random.default_rng(seed)
        self.drift_per_kf = drift_per_kf
        self.drift_noise = drift_noise
        self.camera = camera
        self.n_landmarks = n_landmarks
        self.sigma = float(sigma0)  # metres per current VO unit
        self.T_vo_cur = np.eye(4)
        self.k = 0
        self.sigma_at_kf: list[float] = []  # metres per keyframe unit, per keyframe (truth)
        self.T_last_marg: np.ndarray | None = None  # warped by corrections, like the real VO

    def apply_similarity(self, S_new_vo: np.ndarray) -> None:
        """Apply a correction from the back end to the VO state (frame and units)."""
        R_s, t_s, s = sim3.split(S_new_vo)
        T = self.T_vo_cur
        self.T_vo_cur = se3.from_rt(R_s @ T[:3, :3], s * R_s @ T[:3, 3] + t_s)
        self.sigma /= s
        if self.T_last_marg is not None:
            T = self.T_last_marg
            self.T_last_marg = se3.from_rt(R_s @ T[:3, :3], s * R_s @ T[:3, 3] + t_s)

    def next_keyframe(self) -> MarginalizedKeyframe:
        k = self.k
        if k > 0:
            self.sigma *= float(np.exp(self.drift_per_kf + self.drift_noise * self.rng.normal()))
            T_rel = se3.inverse(self.T_true[k - 1]) @ self.T_true[k]
            noise = se3.exp(np.concatenate([self.drift_noise * 0.1 * self.rng.normal(size=3),
                                            self.drift_noise * self.rng.normal(size=3)]))
            T_rel_vo = T_rel @ noise
            T_rel_vo[:3, 3] /= self.sigma
            T = self.T_vo_cur @ T_rel_vo
            U, _, Vt = np.linalg.svd(T[:3, :3])
            self.T_vo_cur = se3.from_rt(U @ Vt, T[:3, 3])
        cam = self.camera
        uv = np.column_stack([self.rng.uniform(40, cam.width_px - 40, self.n_landmarks),
                              self.rng.uniform(20, cam.height_px - 20, self.n_landmarks)])
        a, b, c = inv_depth_plane(k)
        z_true = a + b * uv[:, 0] / cam.width_px + c * uv[:, 1] / cam.height_px
        xi = self.sigma * z_true  # VO inverse depth: 1 / (depth_m / σ)
        image = np.random.default_rng(10_000 + k).integers(0, 255, (cam.height_px, cam.width_px),
                                                            dtype=np.uint8)
        self.sigma_at_kf.append(self.sigma)
        self.k += 1
        T_prev = None if self.T_last_marg is None else se3.inverse(self.T_last_marg) @ self.T_vo_cur
        self.T_last_marg = self.T_vo_cur.copy()
        return MarginalizedKeyframe(kf_id=k, frame_index=k, t_ns=k * 100_000_000, segment_id=0,
                                    T_vo_kf=self.T_vo_cur.copy(), T_prevkf_kf=T_prev,
                                    landmarks_uv_px=uv, landmarks_inv_depth=xi, image=image, camera=cam)


def image_key(image: np.ndarray) -> int:
    """The keyframe index a synthetic image was generated for (found by its hash)."""
    return int.from_bytes(hashlib.blake2b(np.ascontiguousarray(image).tobytes(), digest_size=8).digest(), "little")


class SyntheticDepthSource:
    """Metric inverse depth maps (32, 64) of :class:`SimulatedVO` images, with noise.

    Args:
        n_keyframes: how many keyframe images to know.
        noise_log_sigma: per-cell multiplicative noise (log std).
        bias: multiplicative bias of every map (1.0 = unbiased).
        seed: RNG seed.
    """

    def __init__(self, n_keyframes: int, noise_log_sigma: float = 0.05, bias: float = 1.0,
                 seed: int = 1, camera: PinholeCamera = CAMERA) -> None:
        self._index = {}
        for k in range(n_keyframes):
            img = np.random.default_rng(10_000 + k).integers(0, 255, (camera.height_px, camera.width_px),
                                                              dtype=np.uint8)
            self._index[image_key(img)] = k
        self.noise = noise_log_sigma
        self.bias = bias
        self.rng = np.random.default_rng(seed)
        self.calls = 0

    def inv_depth_map(self, image: np.ndarray, camera: PinholeCamera) -> np.ndarray:
        from metricslam.errors import DepthSourceError

        self.calls += 1
        k = self._index.get(image_key(image))
        if k is None:
            raise DepthSourceError("image is not one of the synthetic keyframes")
        h, w = 32, 64
        W, H = camera.width_px, camera.height_px
        u = (np.arange(w) + 0.5) * W / w - 0.5
        v = (np.arange(h) + 0.5) * H / h - 0.5
        a, b, c = inv_depth_plane(k)
        z = a + b * u[None, :] / W + c * v[:, None] / H
        z = z * self.bias * np.exp(self.noise * self.rng.normal(size=z.shape))
        return z.astype(np.float32)
