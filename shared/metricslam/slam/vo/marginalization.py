"""Exact Schur-complement marginalization of a keyframe and its child landmarks.

Given the window linearized at its current estimate (reprojection factors of the keyframe's
child landmarks plus the existing prior), the landmarks (1x1 blocks) are eliminated first, then
the keyframe's 6x6 pose block; what remains is a dense quadratic prior on the other window
poses (paper §III-C.4). For a fixed linearization point the result is exact: the remaining
variables' covariance equals the corresponding block of the full graph's covariance (tested).

Observations *in* the marginalized keyframe of landmarks hosted elsewhere are dropped by the
caller before marginalizing (as DSO does): keeping them would put those landmarks into the
prior and make it dense over landmarks.
"""

from __future__ import annotations

import numpy as np

from metricslam.geometry import sim3
from metricslam.slam.vo.linear_system import Linearization, Prior, WindowProblem, linearize


def schur_complement(H: np.ndarray, g: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eliminate the coordinates not in ``keep`` from ``δᵀHδ + 2gᵀδ``.

    Args:
        H: (d, d) symmetric information; g: (d,) gradient; keep: (d,) bool mask.

    Returns:
        ``(H_kept, g_kept)`` of the marginal quadratic on the kept coordinates.
    """
    drop = ~keep
    Haa = H[np.ix_(keep, keep)]
    Hab = H[np.ix_(keep, drop)]
    Hbb = H[np.ix_(drop, drop)]
    Hbb = 0.5 * (Hbb + Hbb.T)
    rhs = np.concatenate([Hab.T, g[drop, None]], axis=1)
    try:
        Hbb_inv_Hba_g = np.linalg.solve(Hbb, rhs)
        if not np.all(np.isfinite(Hbb_inv_Hba_g)):
            raise np.linalg.LinAlgError("non-finite solve")
    except np.linalg.LinAlgError:
        # a keyframe with no remaining constraints: its block is singular; the pseudo-inverse
        # marginalizes only the constrained directions
        Hbb_inv_Hba_g = np.linalg.pinv(Hbb, hermitian=True) @ rhs
    H_new = Haa - Hab @ Hbb_inv_Hba_g[:, :-1]
    g_new = g[keep] - Hab @ Hbb_inv_Hba_g[:, -1]
    return 0.5 * (H_new + H_new.T), g_new


def eliminate_landmarks(lin: Linearization) -> tuple[np.ndarray, np.ndarray]:
    """Reduced camera system ``(S (6n, 6n), g (6n,))`` with the (diagonal) landmark block eliminated."""
    Hll = np.where(lin.Hll > 0, lin.Hll, 1e-12)
    inv_ll = 1.0 / Hll
    S = lin.Hpp - (lin.Hpl * inv_ll) @ lin.Hpl.T
    g = lin.bp - lin.Hpl @ (inv_ll * lin.bl)
    return 0.5 * (S + S.T), g


def marginalize_pose(problem: WindowProblem, pose_index: int, huber_px: float) -> Prior:
    """Marginalize pose ``pose_index`` and **all landmarks of** ``problem``.

    ``problem`` must contain exactly the variables and factors to eliminate: every window pose,
    the child landmarks of the marginalized keyframe with all their observations, and the
    current prior. Returns the new prior on the other poses, linearized at their current values.
    """
    lin = linearize(problem, huber_px)
    S, g = eliminate_landmarks(lin)
    n = problem.n_poses
    keep = np.ones(6 * n, dtype=bool)
    keep[6 * pose_index:6 * pose_index + 6] = False
    H_new, g_new = schur_complement(S, g, keep)
    T_keep = np.delete(problem.T_world_kf, pose_index, axis=0)
    return Prior(H_new, g_new, np.array(T_keep, copy=True))


def rescale_prior(prior: Prior, S_new_old: np.ndarray) -> Prior:
    """Express a prior in a world frame related by a similarity ``S_new_old``.

    Right-perturbation tangents ``[ω, v]`` of poses mapped by a similarity of scale ``s`` become
    ``[ω, s·v]``, so ``H' = D H D`` and ``b' = D b`` with ``D = diag(1,1,1,1/s,1/s,1/s)`` per pose.
    """
    sR = S_new_old[:3, :3]
    s = sim3.scale(S_new_old)
    R, t = sR / s, S_new_old[:3, 3]
    n = len(prior.T_lin)
    d = np.tile(np.array([1.0, 1.0, 1.0, 1.0 / s, 1.0 / s, 1.0 / s]), n)
    T_lin = np.array(prior.T_lin, copy=True)
    for T in T_lin:
        T[:3, :3] = R @ T[:3, :3]
        T[:3, 3] = s * R @ T[:3, 3] + t
    return Prior(prior.H * d[:, None] * d[None, :], prior.b * d, T_lin)


def gauge_basis(T_world_kf: np.ndarray) -> np.ndarray:
    """(6n, 7) tangent directions of a global similarity applied to poses (n, 4, 4).

    Column ``k < 3``: rotation about world axis ``k``; ``3..5``: translation; ``6``: scale. In
    right-perturbation tangents pose ``i`` moves by ``[R_iᵀ ω, R_iᵀ (ω × t_i + v + λ t_i)]``.
    """
    n = len(T_world_kf)
    N = np.zeros((6 * n, 7))
    for i, T in enumerate(T_world_kf):
        R, t = T[:3, :3], T[:3, 3]
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1.0
            N[6 * i:6 * i + 3, k] = R.T @ e
            N[6 * i + 3:6 * i + 6, k] = R.T @ np.cross(e, t)
            N[6 * i + 3:6 * i + 6, 3 + k] = R.T @ e
        N[6 * i + 3:6 * i + 6, 6] = R.T @ t
    return N


def project_out_gauge(prior: Prior) -> Prior:
    """Remove the prior's information along the 7 gauge directions at its linearization point.

    Exact marginalization of a gauge-invariant cost gives a prior with no information along
    the similarity directions at *its* linearization point; after later relinearizations those
    directions move, old priors keep spurious information there (the inconsistency FEJ avoids)
    and it showed up as monocular scale drift. The window's gauge is fixed by holding its
    oldest pose, so nothing is lost by projecting: ``H ← P H P``, ``b ← P b`` with ``P`` the
    orthogonal projector onto the complement of the gauge directions.
    """
    if len(prior.T_lin) == 0:
        return prior
    N = gauge_basis(prior.T_lin)
    Q, _ = np.linalg.qr(N)
    P = np.eye(N.shape[0]) - Q @ Q.T
    H = P @ prior.H @ P
    return Prior(0.5 * (H + H.T), P @ prior.b, prior.T_lin)
