"""Relative Sim(3) odometry between keyframes, across the VO corrections the back end issued.

Units bookkeeping. Each keyframe's ``T_vo_kf`` is expressed in the local VO's world frame *at
its marginalization time*. Every correction ``S_new_vo`` the back end hands out (applied by the
pipeline through ``LocalVO.apply_similarity``) changes that frame and its units, so the VO frame
has an *epoch* ``e`` = number of corrections issued so far, and ``C_e = S_e ⋯ S_1`` maps the
epoch-0 VO frame into the epoch-``e`` VO frame. A keyframe received in epoch ``e_k`` has
``S_vo0_kf = C_{e_k}⁻¹ · T_vo_kf`` in the common epoch-0 frame; its scale ``1 / scale(C_{e_k})``
maps the keyframe's own units (those of its landmarks' ξ) to epoch-0 units. The odometry between
keyframes ``j`` and ``k`` is then ``S_j_k = S_vo0_j⁻¹ · S_vo0_k`` (eq. 11's Ŝ), whose scale
carries the unit change. Conventions: ``docs/conventions.md``.
"""

from __future__ import annotations

import threading

import numpy as np

from metricslam.errors import GraphError
from metricslam.geometry import sim3
from metricslam.slam.graph.config import GraphConfig


def orthonormalize(S: np.ndarray) -> np.ndarray:
    """Project a (numerically drifted) 4x4 similarity back onto Sim(3) (SVD of the 3x3 block)."""
    S = np.asarray(S, dtype=float)
    if S.shape != (4, 4) or not np.all(np.isfinite(S)):
        raise GraphError(f"expected a finite 4x4 similarity, got shape {S.shape}")
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    if not s > 0:
        raise GraphError(f"similarity has non-positive scale {s}; check the VO pose input")
    U, _, Vt = np.linalg.svd(S[:3, :3] / s)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return sim3.from_rts(R, S[:3, 3], s)


class VoFrameHistory:
    """Cumulative corrections ``C_e`` (epoch-0 VO frame -> epoch-e VO frame). Thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._C = [np.eye(4)]
        self._C_inv = [np.eye(4)]

    @property
    def epoch(self) -> int:
        """Number of corrections issued so far (the epoch of keyframes arriving now)."""
        with self._lock:
            return len(self._C) - 1

    def issue(self, S_new_vo: np.ndarray) -> int:
        """Record that ``S_new_vo`` (4, 4, VO epoch e -> e+1) was handed out; returns e+1."""
        S = orthonormalize(S_new_vo)
        with self._lock:
            C = orthonormalize(S @ self._C[-1])
            self._C.append(C)
            self._C_inv.append(sim3.inverse(C))
            return len(self._C) - 1

    def C(self, epoch: int) -> np.ndarray:
        """``C_epoch`` (4, 4)."""
        with self._lock:
            if not 0 <= epoch < len(self._C):
                raise GraphError(f"unknown VO epoch {epoch}; {len(self._C)} epochs exist")
            return self._C[epoch].copy()

    def to_epoch0(self, S_vo_x: np.ndarray, epoch: int) -> np.ndarray:
        """Map a pose/similarity given in the epoch-``epoch`` VO frame into the epoch-0 frame."""
        with self._lock:
            if not 0 <= epoch < len(self._C_inv):
                raise GraphError(f"unknown VO epoch {epoch}; {len(self._C_inv)} epochs exist")
            C_inv = self._C_inv[epoch]
        return orthonormalize(C_inv @ orthonormalize(S_vo_x))


def relative_sim3(S_vo0_j: np.ndarray, S_vo0_k: np.ndarray) -> np.ndarray:
    """``S_j_k = S_vo0_j⁻¹ S_vo0_k`` (4, 4): maps keyframe-k coordinates (k's units) into
    keyframe-j coordinates (j's units)."""
    return orthonormalize(sim3.inverse(S_vo0_j) @ S_vo0_k)


def resolve_epoch(
    history: VoFrameHistory, S_vo0_j: np.ndarray, epoch_j: int, T_vo_kf: np.ndarray,
    T_prevkf_kf: np.ndarray | None, epoch_now: int, max_back: int = 3, tol: float = 1e-3,
) -> tuple[int, np.ndarray, bool]:
    """The epoch keyframe ``k`` was *marginalized* in, which may precede its delivery.

    A VO that marginalizes in a worker thread can queue a keyframe, receive a correction, and
    deliver the keyframe afterwards: its ``T_vo_kf`` is then in the previous frame. The VO's own
    ``T_prevkf_kf`` (relative to keyframe ``j``, frame-independent up to units) tells which
    epoch is consistent: for epoch ``e`` the odometry from ``T_vo_kf`` must equal ``T_prevkf_kf``
    scaled by ``scale(C_{e_j}) / scale(C_e)``. Tries ``epoch_now, epoch_now − 1, …``.

    Returns:
        ``(epoch_k, S_vo0_k, consistent)``; with ``consistent=False`` (no ``T_prevkf_kf`` or no
        epoch matches) ``epoch_now`` is used.
    """
    S_now = history.to_epoch0(T_vo_kf, epoch_now)
    if T_prevkf_kf is None:
        return epoch_now, S_now, False
    T_p = np.asarray(T_prevkf_kf, dtype=float)
    s_j = sim3.scale(history.C(epoch_j))
    for e in range(epoch_now, max(epoch_j, epoch_now - max_back) - 1, -1):
        S_k = S_now if e == epoch_now else history.to_epoch0(T_vo_kf, e)
        r = s_j / sim3.scale(history.C(e))
        S_expected = orthonormalize(sim3.from_rts(T_p[:3, :3], r * T_p[:3, 3], r))
        S_rel = relative_sim3(S_vo0_j, S_k)
        err = float(np.linalg.norm(sim3.local(S_expected, S_rel)))
        if err < tol * (1.0 + float(np.linalg.norm(S_rel[:3, 3]))):
            return e, S_k, True
    return epoch_now, S_now, False


def odometry_sigmas(S_j_k: np.ndarray, config: GraphConfig) -> np.ndarray:
    """Diagonal sigmas (7,) ``[ω, u, λ]`` for an odometry measurement ``S_j_k``.

    Translation sigma is relative to the step length in keyframe-j units (unit-free), with a
    floor; rotation and log-scale sigmas are per step.
    """
    step = float(np.linalg.norm(S_j_k[:3, 3]))
    sig_t = max(config.odom_sigma_trans_rel * step, config.odom_sigma_trans_min)
    return np.array([config.odom_sigma_rot_rad] * 3 + [sig_t] * 3 + [config.odom_sigma_log_scale])


def odometry_information(
    S_j_k: np.ndarray, information_se3: np.ndarray | None, config: GraphConfig
) -> np.ndarray:
    """7x7 information of ``S_j_k`` in ``[ω, u, λ]``.

    With ``config.use_vo_information`` and a VO-provided 6x6 information of ``T_prevkf_kf``
    (tangent ``[ω, v]``, keyframe-k units), the translation block is rescaled into keyframe-j
    units (``σ_j = scale(S_j_k)·σ_k``) and the log-scale gets ``odom_sigma_log_scale``;
    otherwise the diagonal :func:`odometry_sigmas` are used.
    """
    if config.use_vo_information and information_se3 is not None:
        info6 = np.asarray(information_se3, dtype=float)
        if info6.shape != (6, 6) or not np.all(np.isfinite(info6)):
            raise GraphError(f"VO information must be a finite 6x6 matrix, got shape {info6.shape}")
        r = sim3.scale(S_j_k)
        D = np.diag([1.0, 1.0, 1.0, 1.0 / r, 1.0 / r, 1.0 / r])
        info = np.zeros((7, 7))
        info[:6, :6] = D @ info6 @ D
        info[6, 6] = 1.0 / config.odom_sigma_log_scale**2
        return info
    return np.diag(1.0 / odometry_sigmas(S_j_k, config) ** 2)
