"""Two-view monocular initialization: essential matrix, relative pose, triangulation, parallax.

A stationary or slow start yields ``None`` (keep waiting) rather than a guessed map: the
reference frame is only accepted once the median corner motion, the number of essential-matrix
inliers and the median triangulation angle all pass their thresholds. The baseline between the
two views is fixed to length 1 (the monocular scale, in "VO units").

The frames tracked between the two views then get poses against the two-view points
(:func:`pending_poses`), and a start whose points do not explain those frames is reported
(``VOConfig.init_pending_min_share``; ``docs/history/rule_vo_init_pending_session22.md``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.geometry import se3, so3
from metricslam.slam.vo.config import VOConfig
from metricslam.slam.vo.motion_only import estimate_pose
from metricslam.slam.vo.reprojection import triangulate_inverse_depth

log = logging.getLogger(__name__)


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
    pending: list  # (frame_index, t_ns, ids (N,), uv_px (N, 2)) of the frames tracked since the reference


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


def pending_poses(camera: PinholeCamera, config: VOConfig, ref: InitRef, res: InitResult,
                  T_ref_cur: np.ndarray, t_cur_ns: int) -> list[tuple[int, np.ndarray, float]]:
    """``(frame_index, T_ref_f (4, 4), inlier share)`` of each frame tracked between the two views.

    Each pose is motion-only BA of the frame's tracks against the two-view points (``res.ids`` at
    ``res.rho_ref``, scaled to the units of ``T_ref_cur``, the start's relative pose in the units the
    map is built in), started at the pose interpolated along the two-view motion; where fewer than
    ``min_tracked_landmarks`` points agree with it, it stays interpolated (share NaN).
    Interpolation alone is degrees off where a turn starts between the views.
    """
    scale = float(np.linalg.norm(T_ref_cur[:3, 3]) / np.linalg.norm(res.T_ref_cur[:3, 3]))
    pos = {int(i): k for k, i in enumerate(ref.ids)}
    uv_ref = np.array([ref.uv_px[pos[int(i)]] for i in res.ids]).reshape(-1, 2)
    p_ref = np.c_[camera.normalized(uv_ref), np.ones(len(res.ids))] * (scale / res.rho_ref)[:, None]
    span = max(t_cur_ns - ref.t_ns, 1)
    w = so3.log(T_ref_cur[:3, :3])
    out = []
    for idx, t_ns, ids, uv_px in ref.pending:
        a = (t_ns - ref.t_ns) / span
        T = se3.from_rt(so3.exp(a * w), a * T_ref_cur[:3, 3])
        _, i_p, i_t = np.intersect1d(res.ids, ids, return_indices=True)
        share = float("nan")
        if len(i_p) >= config.min_tracked_landmarks:
            T_pnp, inl = estimate_pose(T, p_ref[i_p], uv_px[i_t], camera.K, config.huber_px, config.pose_iterations)
            if int(inl.sum()) >= config.min_tracked_landmarks:
                T, share = T_pnp, float(inl.mean())
        out.append((int(idx), T, share))
    return out


def start_confirmed(config: VOConfig, poses: list[tuple[int, np.ndarray, float]], ref_index: int,
                    cur_index: int) -> bool:
    """False (and a warning logged) when some frame between the two views, reference frame
    ``ref_index`` and current frame ``cur_index``, has fewer than ``init_pending_min_share`` of its
    two-view points agreeing with its best pose (:func:`pending_poses`): the start's relative pose
    does not explain the frames it spans (tracks aliased where a turn starts gave a wrong
    essential matrix). True without such frames."""
    shares = [s for _, _, s in poses if np.isfinite(s)]
    if not shares or min(shares) >= config.init_pending_min_share:
        return True
    log.warning("frame %d: the VO's two-view start from frame %d does not explain the frames between "
                "(%.2f of a frame's points agree; docs/vo.md, 'Aliased tracks')", cur_index, ref_index, min(shares))
    return False
