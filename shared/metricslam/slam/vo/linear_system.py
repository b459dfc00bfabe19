"""The window's normal equations: poses (6-D blocks) + inverse depths (1x1 blocks) + a prior.

The cost is ``E = Σ huber(|r|²) + δᵀ H_prior δ + 2 b_priorᵀ δ`` with pixel noise σ = 1, so the
Gauss-Newton Hessian ``H = Σ Jᵀ W J`` is the information matrix and ``H⁻¹`` the covariance.
``δ_i = Log(T_lin_i⁻¹ T_world_i)`` (right perturbation) is how far pose ``i`` moved from the
prior's linearization point; the prior's Jacobian is taken as identity (first order).

Layout: pose ``i`` owns rows ``6i .. 6i+5`` (tangent ``[ω, v]``); landmark ``j`` is column ``j``
of ``H_pl``. ``H_ll`` is diagonal because each landmark is one scalar. See
``docs/conventions.md`` for frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from metricslam.slam.vo import lie
from metricslam.slam.vo.reprojection import huber_cost, huber_weights, project


@dataclass
class Prior:
    """A dense quadratic prior ``δᵀ H δ + 2 bᵀ δ`` on window poses.

    Attributes:
        H: (6n, 6n) information; b: (6n,) gradient at the linearization point.
        T_lin: (n, 4, 4) world poses at which it was linearized.
    """

    H: np.ndarray
    b: np.ndarray
    T_lin: np.ndarray

    def deltas(self, T_world_kf: np.ndarray) -> np.ndarray:
        """Stacked ``δ`` (6n,) of poses (n, 4, 4) from the linearization point."""
        if len(T_world_kf) == 0:
            return np.zeros(0)
        return lie.local(self.T_lin, np.asarray(T_world_kf)).reshape(-1)

    def cost(self, T_world_kf: np.ndarray) -> float:
        if not np.any(self.H) and not np.any(self.b):
            return 0.0
        d = self.deltas(T_world_kf)
        return float(d @ self.H @ d + 2.0 * self.b @ d)


@dataclass
class WindowProblem:
    """Plain arrays describing the window (indices are positions in these arrays).

    Attributes:
        T_world_kf: (n, 4, 4) keyframe poses (VO world).
        lm_host: (m,) host keyframe index of each landmark.
        lm_bearing: (m, 3) host bearings ``K⁻¹ [u, v, 1]``.
        lm_rho: (m,) inverse depths (1/VO-units).
        obs_lm, obs_kf: (o,) landmark and observing keyframe of each observation (never the host).
        obs_uv_px: (o, 2) observed pixels.
        K: (3, 3) intrinsics.
        prior: dense prior over the n poses, or None.
    """

    T_world_kf: np.ndarray
    lm_host: np.ndarray
    lm_bearing: np.ndarray
    lm_rho: np.ndarray
    obs_lm: np.ndarray
    obs_kf: np.ndarray
    obs_uv_px: np.ndarray
    K: np.ndarray
    prior: Prior | None = field(default=None)
    #: cached summation plans (depend only on the structure; shared by ``with_values`` copies)
    plans: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def n_poses(self) -> int:
        return len(self.T_world_kf)

    @property
    def n_landmarks(self) -> int:
        return len(self.lm_rho)

    def with_values(self, T_world_kf: np.ndarray, lm_rho: np.ndarray) -> "WindowProblem":
        return replace(self, T_world_kf=T_world_kf, lm_rho=lm_rho)


@dataclass(frozen=True)
class Linearization:
    """Normal equations ``[[Hpp, Hpl], [Hlp, diag(Hll)]] δ = −[bp, bl]`` and the cost."""

    Hpp: np.ndarray  # (6n, 6n)
    Hpl: np.ndarray  # (6n, m)
    Hll: np.ndarray  # (m,)
    bp: np.ndarray  # (6n,)
    bl: np.ndarray  # (m,)
    cost: float


def residuals(problem: WindowProblem, with_jacobians: bool = False):
    """Projection of every observation (see :func:`reprojection.project`)."""
    P = problem
    lm = P.obs_lm
    return project(P.T_world_kf[P.lm_host[lm]], P.T_world_kf[P.obs_kf], P.lm_bearing[lm],
                   P.lm_rho[lm], P.obs_uv_px, P.K, with_jacobians=with_jacobians)


def total_cost(problem: WindowProblem, huber_px: float) -> float:
    """Robust reprojection cost plus prior cost."""
    proj = residuals(problem)
    c = huber_cost(proj.residual_px, huber_px)
    c = np.where(proj.valid, c, 4.0 * huber_px * 100.0)  # behind the camera: large, finite
    prior = problem.prior.cost(problem.T_world_kf) if problem.prior is not None else 0.0
    return float(np.sum(c)) + prior


def linearize(problem: WindowProblem, huber_px: float) -> Linearization:
    """Build the Huber-weighted Gauss-Newton normal equations of the window."""
    P = problem
    n, m = P.n_poses, P.n_landmarks
    proj = residuals(P, with_jacobians=True)
    w = huber_weights(proj.residual_px, huber_px) * proj.valid
    r = proj.residual_px
    Jh, Jt, Jr = proj.J_host, proj.J_target, proj.J_rho
    host = P.lm_host[P.obs_lm]
    tgt = P.obs_kf
    WJh = Jh * w[:, None, None]
    WJt = Jt * w[:, None, None]

    JhWr = np.einsum("nki,nk->ni", WJh, r)
    JtWr = np.einsum("nki,nk->ni", WJt, r)
    JhWJr = np.einsum("nki,nk->ni", WJh, Jr)
    JtWJr = np.einsum("nki,nk->ni", WJt, Jr)
    # batched (6x2)(2x6) products: matmul is ~5x faster than einsum here
    WJhT, WJtT = np.transpose(WJh, (0, 2, 1)), np.transpose(WJt, (0, 2, 1))
    hh = np.matmul(WJhT, Jh).reshape(-1, 36)
    tt = np.matmul(WJtT, Jt).reshape(-1, 36)
    ht = np.matmul(WJhT, Jt)
    th = np.transpose(ht, (0, 2, 1)).reshape(-1, 36)
    # sorted segment sums with a cached plan (much faster than np.add.at on (n, n, 6, 6))
    if "pp" not in P.plans:
        P.plans["pp"] = SumPlan(np.concatenate([host * n + host, tgt * n + tgt, host * n + tgt,
                                                tgt * n + host]), n * n)
        P.plans["p"] = SumPlan(np.concatenate([host, tgt]), n)
        P.plans["lm"] = SumPlan(P.obs_lm, m)
    vals = np.concatenate([hh, tt, ht.reshape(-1, 36), th])
    Hpp = P.plans["pp"].sum(vals).reshape(n, n, 6, 6).transpose(0, 2, 1, 3).reshape(6 * n, 6 * n)

    # a landmark's host block sums over its observations; each (target, landmark) is unique
    Hpl3 = np.zeros((n, m, 6))
    Hpl3[P.lm_host, np.arange(m)] = P.plans["lm"].sum(JhWJr)
    Hpl3[tgt, P.obs_lm] += JtWJr
    Hpl = Hpl3.transpose(0, 2, 1).reshape(6 * n, m)

    Hll = np.bincount(P.obs_lm, weights=w * np.sum(Jr * Jr, axis=1), minlength=m)
    bl = np.bincount(P.obs_lm, weights=w * np.sum(Jr * r, axis=1), minlength=m)
    bp = P.plans["p"].sum(np.concatenate([JhWr, JtWr])).reshape(6 * n)

    cost = float(np.sum(np.where(proj.valid, huber_cost(r, huber_px), 4.0 * huber_px * 100.0)))
    if P.prior is not None:
        d = P.prior.deltas(P.T_world_kf)
        Hpp = Hpp + P.prior.H
        bp = bp + P.prior.H @ d + P.prior.b
        cost += float(d @ P.prior.H @ d + 2.0 * P.prior.b @ d)
    return Linearization(Hpp, Hpl, Hll, bp, bl, cost)


class SumPlan:
    """Sums rows of (K, d) arrays that share a key in ``[0, n_keys)`` (sort once, reuse)."""

    def __init__(self, keys: np.ndarray, n_keys: int) -> None:
        self.n_keys = n_keys
        self.order = np.argsort(keys, kind="stable")
        k = keys[self.order]
        self.starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]]) if len(k) else np.zeros(0, int)
        self.targets = k[self.starts] if len(k) else np.zeros(0, int)

    def sum(self, values: np.ndarray) -> np.ndarray:
        """(K, d) -> (n_keys, d)."""
        out = np.zeros((self.n_keys, values.shape[1]))
        if len(self.order):
            out[self.targets] = np.add.reduceat(values[self.order], self.starts, axis=0)
        return out


def dense_hessian(lin: Linearization) -> tuple[np.ndarray, np.ndarray]:
    """The full (6n+m)² Hessian and gradient (for tests and marginalization)."""
    Hll = np.diag(lin.Hll)
    H = np.block([[lin.Hpp, lin.Hpl], [lin.Hpl.T, Hll]])
    return H, np.concatenate([lin.bp, lin.bl])
