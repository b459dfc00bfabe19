"""Relative Sim(3) odometry between keyframes, across the VO corrections the back end issued.

Units bookkeeping. Each keyframe's ``T_vo_kf`` is expressed in the local VO's world frame *at
its marginalization time*. Every correction ``S_new_vo`` the back end hands out (applied by the
pipeline through ``LocalVO.apply_similarity``) changes that frame and its units, so the VO frame
has an *epoch* ``e`` = number of corrections issued so far. ``M_{a→b} = S_b ⋯ S_{a+1}`` maps
the epoch-``a`` VO frame into the epoch-``b`` frame. The odometry between keyframes ``j``
(epoch ``e_j``) and ``k`` (epoch ``e_k``) is ``S_j_k = T_vo_j⁻¹ · M_{e_j→e_k}⁻¹ · T_vo_k``
(eq. 11's Ŝ): it maps k's coordinates in k's units (those of its landmarks' ξ) into j's, and its
scale carries the unit change. Conventions: ``docs/conventions.md``.
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
    s = sim3.scale(S)
    if not s > 0:
        raise GraphError(f"similarity has non-positive scale {s}; check the VO pose input")
    U, _, Vt = np.linalg.svd(S[:3, :3] / s)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return sim3.from_rts(R, S[:3, 3], s)


class VoFrameHistory:
    """The corrections ``S_1, S_2, …`` handed out so far (``S_e`` maps the epoch ``e−1`` VO frame
    to the epoch ``e`` frame). Thread-safe.

    Only the corrections *between* two epochs are ever composed (:meth:`between`): composing
    all of them into an epoch-0 frame is exact in algebra but not in floating point once the
    VO's units have been rescaled thousands of times (the product's scale runs to 1e±40).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._S: list[np.ndarray] = []

    @property
    def epoch(self) -> int:
        """Number of corrections issued so far (the epoch of keyframes arriving now)."""
        with self._lock:
            return len(self._S)

    def issue(self, S_new_vo: np.ndarray) -> int:
        """Record that ``S_new_vo`` (4, 4, VO epoch e -> e+1) was handed out; returns e+1."""
        S = orthonormalize(S_new_vo)
        with self._lock:
            self._S.append(S)
            return len(self._S)

    def between(self, e_from: int, e_to: int) -> np.ndarray:
        """``M = S_{e_to} ⋯ S_{e_from+1}`` (4, 4): maps the epoch-``e_from`` VO frame into the
        epoch-``e_to`` frame (identity when equal; the inverse map when ``e_to < e_from``)."""
        with self._lock:
            n = len(self._S)
            if not (0 <= e_from <= n and 0 <= e_to <= n):
                raise GraphError(f"unknown VO epoch ({e_from} -> {e_to}); {n + 1} epochs exist")
            lo, hi = min(e_from, e_to), max(e_from, e_to)
            factors = self._S[lo:hi]
        M = np.eye(4)
        for S in factors:
            M = S @ M
        M = orthonormalize(M)
        return M if e_to >= e_from else sim3.inverse(M)


def relative_sim3(T_vo_j: np.ndarray, T_vo_k: np.ndarray, M_j_to_k: np.ndarray | None = None) -> np.ndarray:
    """``S_j_k = T_vo_j⁻¹ · M⁻¹ · T_vo_k`` (4, 4): maps keyframe-k coordinates (k's units) into
    keyframe-j coordinates (j's units).

    Args:
        T_vo_j / T_vo_k: keyframe poses, each in the VO frame of its own epoch.
        M_j_to_k: :meth:`VoFrameHistory.between` (j's epoch -> k's epoch); None if the same.
    """
    S_k_in_j_epoch = T_vo_k if M_j_to_k is None else sim3.inverse(M_j_to_k) @ T_vo_k
    return orthonormalize(sim3.inverse(orthonormalize(T_vo_j)) @ orthonormalize(S_k_in_j_epoch))


def resolve_epoch(
    history: VoFrameHistory, T_vo_j: np.ndarray, epoch_j: int, T_vo_kf: np.ndarray,
    T_prevkf_kf: np.ndarray | None, epoch_now: int, max_back: int = 3, tol: float = 1e-3,
) -> tuple[int, np.ndarray, bool]:
    """The epoch keyframe ``k`` was *marginalized* in, which may precede its delivery.

    A VO that marginalizes in a worker thread can queue a keyframe, receive a correction, and
    deliver the keyframe afterwards: its ``T_vo_kf`` is then in the previous frame. The VO's own
    ``T_prevkf_kf`` (relative to keyframe ``j``, frame-independent up to units) tells which
    epoch is consistent: for epoch ``e`` the odometry from ``T_vo_kf`` must equal ``T_prevkf_kf``
    in j's units, i.e. scaled by ``1 / scale(M_{e_j→e})``. Tries ``epoch_now, epoch_now − 1, …``.

    Returns:
        ``(epoch_k, S_j_k, consistent)``; with ``consistent=False`` (no ``T_prevkf_kf`` or no
        epoch matches) ``epoch_now`` is used.
    """
    S_now = relative_sim3(T_vo_j, T_vo_kf, history.between(epoch_j, epoch_now))
    if T_prevkf_kf is None:
        return epoch_now, S_now, False
    T_p = np.asarray(T_prevkf_kf, dtype=float)
    for e in range(epoch_now, max(epoch_j, epoch_now - max_back) - 1, -1):
        M = history.between(epoch_j, e)
        S_rel = S_now if e == epoch_now else relative_sim3(T_vo_j, T_vo_kf, M)
        r = 1.0 / sim3.scale(M)
        S_expected = orthonormalize(sim3.from_rts(T_p[:3, :3], r * T_p[:3, 3], r))
        err = float(np.linalg.norm(sim3.local(S_expected, S_rel)))
        if err < tol * (1.0 + float(np.linalg.norm(S_rel[:3, 3]))):
            return e, S_rel, True
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
