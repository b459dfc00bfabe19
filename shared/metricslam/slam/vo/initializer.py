"""Two-view monocular initialization: essential matrix, relative pose, triangulation, parallax.

A stationary or slow start yields ``None`` (keep waiting) rather than a guessed map: the
reference frame is only accepted once the median corner motion, the number of essential-matrix
inliers and the median triangulation angle all pass their thresholds. The baseline between the
two views is fixed to length 1 (the monocular scale, in "VO units").
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.slam.vo.config import VOConfig
from metricslam.slam.vo.reprojection import triangulate_inverse_depth


@dataclass(frozen=True)
class InitResult:
    """An accepted two-view initialization.

    Attributes:
        T_ref_cur: (4, 4) pose of the current frame in the reference frame, ``|t| = 1``.
        ids: (M,) track ids of the inlier correspondences with positive depth.
        rho_ref: (M,) their inverse depths in the reference frame (1/VO-units).
        parallax_deg: median triangulation angle.
    """

    T_ref_cur: np.ndarray
    ids: np.ndarray
    rho_ref: np.ndarray
    parallax_deg: float


@dataclass
class InitRef:
    """The reference frame a two-view initialization waits on (``LocalVO`` keeps one)."""

    frame_index: int
    t_ns: int
    image: np.ndarray
    ids: np.ndarray
    uv_px: np.ndarray
    T_world_ref: np.ndarray
    pending: list  # (frame_index, t_ns) of frames processed since the reference


def try_initialize(config: VOConfig, camera: PinholeCamera, ids_ref: np.ndarray,
                   uv_ref_px: np.ndarray, ids_cur: np.ndarray, uv_cur_px: np.ndarray) -> InitResult | None:
    """Attempt initialization between a reference frame and the current frame; None = not yet."""
    common, i_ref, i_cur = np.intersect1d(ids_ref, ids_cur, return_indices=True)
    if len(common) < config.init_min_inliers:
        return None
    a_px, b_px = uv_ref_px[i_ref], uv_cur_px[i_cur]
    if np.median(np.linalg.norm(a_px - b_px, axis=1)) < config.init_min_motion_px:
        return None
    a, b = camera.normalized(a_px), camera.normalized(b_px)
    thr = config.ransac_threshold_px / camera.fx_px
    E, mask = cv2.findEssentialMat(a, b, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=thr)
    if E is None or E.shape != (3, 3) or mask is None:
        return None
    n_in, R_cur_ref, t_cur_ref, mask2 = cv2.recoverPose(E, a, b, np.eye(3), mask=mask.copy())
    inl = mask2.ravel() > 0
    if n_in < config.init_min_inliers:
        return None
    t = t_cur_ref.ravel() / np.linalg.norm(t_cur_ref)
    T_cur_ref = np.eye(4)
    T_cur_ref[:3, :3], T_cur_ref[:3, 3] = R_cur_ref, t
    T_ref_cur = np.linalg.inv(T_cur_ref)
    n = int(inl.sum())
    bearing = np.concatenate([a[inl], np.ones((n, 1))], axis=1)
    rho, parallax = triangulate_inverse_depth(np.repeat(np.eye(4)[None], n, 0),
                                              np.repeat(T_ref_cur[None], n, 0), bearing, b[inl])
    good = np.isfinite(rho) & (rho > 0)
    if good.sum() < config.init_min_inliers:
        return None
    med_parallax_deg = float(np.degrees(np.median(parallax[good])))
    if med_parallax_deg < config.init_min_parallax_deg:
        return None
    return InitResult(T_ref_cur, common[inl][good], rho[good], med_parallax_deg)
