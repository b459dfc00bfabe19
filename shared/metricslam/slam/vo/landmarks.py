"""Landmarks as in the paper: host keyframe, host pixel ``u_j`` and inverse depth ``ξ_j``.

:class:`LandmarkMap` owns the landmarks of the window and their observations (keyframe id ->
pixel), and flattens them into the arrays of a
:class:`~metricslam.slam.vo.linear_system.WindowProblem`. Not thread-safe by itself: the
:class:`~metricslam.slam.vo.local_vo.LocalVO` lock guards it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.slam.vo.linear_system import Prior, WindowProblem


@dataclass
class Landmark:
    """One landmark.

    Attributes:
        lm_id: unique id (equals the frontend track id that created it).
        host_kf: id of the keyframe it was detected in.
        uv_host_px: (2,) pixel in the host keyframe.
        bearing: (3,) ``K⁻¹ [u, v, 1]``.
        rho: inverse depth in the host frame (1/VO-units); meaningful when ``has_depth``.
        has_depth: True once triangulated with enough parallax.
        obs: keyframe id -> (2,) observed pixel (never the host).
    """

    lm_id: int
    host_kf: int
    uv_host_px: np.ndarray
    bearing: np.ndarray
    rho: float = 1.0
    has_depth: bool = False
    obs: dict[int, np.ndarray] = field(default_factory=dict)


class LandmarkMap:
    """Window landmarks keyed by id."""

    def __init__(self, camera: PinholeCamera) -> None:
        self.camera = camera
        self.landmarks: dict[int, Landmark] = {}

    def __len__(self) -> int:
        return len(self.landmarks)

    def add(self, lm_id: int, host_kf: int, uv_px: np.ndarray, rho: float | None = None) -> Landmark:
        bearing = np.r_[self.camera.normalized(uv_px[None])[0], 1.0]
        lm = Landmark(int(lm_id), int(host_kf), np.array(uv_px, dtype=float), bearing,
                      rho=1.0 if rho is None else float(rho), has_depth=rho is not None)
        self.landmarks[lm.lm_id] = lm
        return lm

    def add_many(self, lm_ids: np.ndarray, host_kf: int, uv_px: np.ndarray,
                 rho: np.ndarray | None = None) -> list[Landmark]:
        """Vectorized :meth:`add` for (N,) ids and (N, 2) host pixels (``rho`` None: no depth)."""
        uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
        xy = self.camera.normalized(uv) if len(uv) else np.zeros((0, 2))
        out = []
        for k, lid in enumerate(lm_ids):
            lm = Landmark(int(lid), int(host_kf), uv[k].copy(), np.array([xy[k, 0], xy[k, 1], 1.0]),
                          rho=1.0 if rho is None else float(rho[k]), has_depth=rho is not None)
            self.landmarks[lm.lm_id] = lm
            out.append(lm)
        return out

    def children(self, kf_id: int) -> list[Landmark]:
        return [lm for lm in self.landmarks.values() if lm.host_kf == kf_id]

    def remove_keyframe(self, kf_id: int) -> list[Landmark]:
        """Delete the keyframe's child landmarks and its observations of others; returns children."""
        kids = self.children(kf_id)
        for lm in kids:
            del self.landmarks[lm.lm_id]
        for lm in self.landmarks.values():
            lm.obs.pop(kf_id, None)
        return kids

    def problem(self, kf_ids: list[int], T_world_kf: np.ndarray, prior: Prior | None,
                only_hosts: set[int] | None = None) -> tuple[WindowProblem, list[int]]:
        """Flatten depth-known landmarks with at least one observation into a problem.

        Args:
            kf_ids: window keyframe ids, in the order of ``T_world_kf`` (n, 4, 4).
            only_hosts: if given, include only landmarks hosted in these keyframes.

        Returns:
            ``(problem, lm_ids)`` with ``lm_ids[j]`` the id of landmark column ``j``.
        """
        index = {k: i for i, k in enumerate(kf_ids)}
        lm_ids, host, bearing, rho = [], [], [], []
        obs_lm, obs_kf, obs_uv = [], [], []
        for lm in self.landmarks.values():  # the hot loop of every solve: plain Python, no numpy
            if not lm.has_depth:
                continue
            h = index.get(lm.host_kf)
            if h is None or (only_hosts is not None and lm.host_kf not in only_hosts):
                continue
            j = len(lm_ids)
            n_before = len(obs_kf)
            for k, uv in lm.obs.items():
                i = index.get(k)
                if i is not None:
                    obs_kf.append(i)
                    obs_uv.append(uv)
            if len(obs_kf) == n_before:
                continue
            obs_lm.extend([j] * (len(obs_kf) - n_before))
            lm_ids.append(lm.lm_id)
            host.append(h)
            bearing.append(lm.bearing)
            rho.append(lm.rho)
        problem = WindowProblem(
            T_world_kf=np.array(T_world_kf, dtype=float).reshape(-1, 4, 4),
            lm_host=np.array(host, dtype=np.int64), lm_bearing=np.array(bearing).reshape(-1, 3),
            lm_rho=np.array(rho, dtype=float), obs_lm=np.array(obs_lm, dtype=np.int64),
            obs_kf=np.array(obs_kf, dtype=np.int64), obs_uv_px=np.array(obs_uv).reshape(-1, 2),
            K=self.camera.K, prior=prior)
        return problem, lm_ids

    def points_world(self, lm_ids: np.ndarray, T_world_by_kf: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """World points (K, 3) of depth-known landmarks among ``lm_ids``; returns ``(mask, points)``."""
        mask = np.zeros(len(lm_ids), dtype=bool)
        rows, hosts, bearing, rho = [], [], [], []
        get = self.landmarks.get
        for k, lid in enumerate(np.asarray(lm_ids).tolist()):
            lm = get(lid)
            if lm is None or not lm.has_depth:
                continue
            T = T_world_by_kf.get(lm.host_kf)
            if T is None:
                continue
            rows.append(k)
            hosts.append(T)
            bearing.append(lm.bearing)
            rho.append(lm.rho)
        if not rows:
            return mask, np.zeros((0, 3))
        mask[rows] = True
        T_h = np.array(hosts)
        p_host = np.array(bearing) / np.array(rho)[:, None]
        return mask, np.matmul(T_h[:, :3, :3], p_host[:, :, None])[:, :, 0] + T_h[:, :3, 3]

    def predict_pixels(self, lm_ids: np.ndarray, T_world_by_kf: dict[int, np.ndarray],
                       T_world_cam: np.ndarray) -> np.ndarray:
        """Where landmarks should appear (N, 2) for a predicted camera pose; NaN if unknown.

        Landmarks without a depth yet use the median inverse depth of those with one.
        """
        out = np.full((len(lm_ids), 2), np.nan)
        rhos = [lm.rho for lm in self.landmarks.values() if lm.has_depth]
        rho_med = float(np.median(rhos)) if rhos else None
        rows, hosts, bearing, rho = [], [], [], []
        get = self.landmarks.get
        for k, lid in enumerate(np.asarray(lm_ids).tolist()):  # Python ints: no numpy scalars
            lm = get(lid)
            if lm is None or lm.host_kf not in T_world_by_kf:
                continue
            if not lm.has_depth and rho_med is None:
                continue
            rows.append(k)
            hosts.append(T_world_by_kf[lm.host_kf])
            bearing.append(lm.bearing)
            rho.append(lm.rho if lm.has_depth else rho_med)
        if not rows:
            return out
        T_h = np.array(hosts)
        T_cw = np.linalg.inv(T_world_cam)
        R = np.einsum("ij,njk->nik", T_cw[:3, :3], T_h[:, :3, :3])
        t = np.einsum("ij,nj->ni", T_cw[:3, :3], T_h[:, :3, 3]) + T_cw[:3, 3]
        q = np.einsum("nij,nj->ni", R, np.array(bearing)) + np.array(rho)[:, None] * t
        ok = q[:, 2] > 1e-6
        uv = self.camera.project(np.where(ok[:, None], q, np.nan))
        out[np.array(rows)] = uv
        return out
