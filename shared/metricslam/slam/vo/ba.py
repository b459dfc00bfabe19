"""Sliding-window bundle adjustment: Levenberg-Marquardt on poses + inverse depths (numpy).

Why hand-written numpy instead of gtsam: with landmarks that are one scalar each (pixel fixed in
the host keyframe, as in the paper and DSO), the landmark block of the Hessian is diagonal, so
the reduced camera system is a dense (6n x 6n) matrix (n <= ~10 keyframes) built with a few
vectorized ``einsum``/``add.at`` calls; one LM iteration over ~2000 observations costs a few
ms. gtsam would need Python ``CustomFactor``s for this residual (measured slow, DESIGN.md) or
3-D point factors, which are indeterminate for low-parallax points. The same normal equations
give exact Schur-complement marginalization (``marginalization.py``) for free.

Gauge: the window is invariant to a 7-D similarity. The first pose is held fixed (6-D) and LM's
damping keeps the remaining scale direction still (the marginalization prior carries no
information along gauge directions, see ``marginalization.project_out_gauge``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from metricslam.geometry import so3
from metricslam.slam.vo import lie
from metricslam.slam.vo.linear_system import WindowProblem, linearize

#: inverse depths are kept above this fraction of the median (points at infinity are fine,
#: negative depth is not)
_MIN_RHO_FRACTION = 1e-4


@dataclass(frozen=True)
class BAResult:
    T_world_kf: np.ndarray  # (n, 4, 4)
    lm_rho: np.ndarray  # (m,)
    initial_cost: float
    final_cost: float
    iterations: int


def orthonormalized(T: np.ndarray) -> np.ndarray:
    """``T`` with its rotation block projected back onto SO(3) (undo round-off drift)."""
    out = np.array(T, dtype=float, copy=True)
    out[:3, :3] = so3.project_to_so3(out[:3, :3])
    return out


def solve_reduced(Hpp: np.ndarray, Hpl: np.ndarray, Hll: np.ndarray, bp: np.ndarray,
                  bl: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve the normal equations by the landmark Schur complement.

    Args:
        free: (6n,) bool mask of pose coordinates to solve (the others stay 0).

    Returns:
        ``(dp (6n,), dl (m,))``, the Gauss-Newton step.
    """
    inv_ll = 1.0 / Hll
    S = Hpp - (Hpl * inv_ll) @ Hpl.T
    rhs = -bp + Hpl @ (inv_ll * bl)
    dp = np.zeros_like(bp)
    if np.any(free):
        Sf = S[np.ix_(free, free)]
        try:
            dp[free] = np.linalg.solve(Sf, rhs[free])
        except np.linalg.LinAlgError:
            dp[free] = np.linalg.lstsq(Sf, rhs[free], rcond=None)[0]
    dl = -inv_ll * (bl + Hpl.T @ dp)
    return dp, dl


def _apply_step(problem: WindowProblem, dp: np.ndarray, dl: np.ndarray) -> WindowProblem:
    T = lie.retract(problem.T_world_kf, dp.reshape(-1, 6))
    rho = problem.lm_rho + dl
    floor = _MIN_RHO_FRACTION * max(float(np.median(np.abs(problem.lm_rho))), 1e-12) \
        if len(rho) else 0.0
    rho = np.maximum(rho, floor)
    return problem.with_values(T, rho)


def bundle_adjust(problem: WindowProblem, huber_px: float, iterations: int,
                  fixed_poses: tuple[int, ...] = (0,), lambda_init: float = 1e-4) -> BAResult:
    """Levenberg-Marquardt (Marquardt-scaled damping) on the window.

    Args:
        problem: the window; not modified.
        huber_px: Huber threshold (pixels).
        iterations: maximum number of accepted-or-rejected steps.
        fixed_poses: pose indices held constant (gauge).
    """
    n = problem.n_poses
    free = np.ones(6 * n, dtype=bool)
    for i in fixed_poses:
        if 0 <= i < n:
            free[6 * i:6 * i + 6] = False
    lam = lambda_init
    current = problem
    lin = linearize(current, huber_px)
    cost0 = lin.cost
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 -- `it` (iterations run) is returned
        Hpp = lin.Hpp + lam * np.diag(np.diag(lin.Hpp)) + 1e-9 * np.eye(6 * n)
        Hll = lin.Hll * (1.0 + lam) + 1e-9
        dp, dl = solve_reduced(Hpp, lin.Hpl, Hll, lin.bp, lin.bl, free)
        candidate = _apply_step(current, dp, dl)
        cand_lin = linearize(candidate, huber_px)  # its cost decides; reused when accepted
        if np.isfinite(cand_lin.cost) and cand_lin.cost < lin.cost:
            converged = (lin.cost - cand_lin.cost) < 1e-6 * max(lin.cost, 1e-12)
            current, lin = candidate, cand_lin
            lam = max(lam / 3.0, 1e-7)
            if converged:
                break
        else:
            lam *= 8.0
            if lam > 1e6:
                break
    return BAResult(current.T_world_kf, current.lm_rho, cost0, lin.cost, it)
