"""The left Jacobian ``W(ω, λ) = ∫₀¹ e^{λτ} Exp(τω) dτ`` shared by SE(3) (λ = 0) and Sim(3).

``W = a·I + b·Ω + c·Ω²`` with scalar integrals evaluated by 32-point Gauss–Legendre
quadrature. The integrands are entire functions written with ``sinc`` so there is no 0/0 at
θ = 0 or λ = 0; for |θ| ≤ π and |λ| ≤ 10 the quadrature error is below 1e-15.
See ``docs/conventions.md``.
"""

from __future__ import annotations

import numpy as np

from metricslam.geometry import so3

_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(32)
_TAU = 0.5 * (_NODES + 1.0)  # nodes mapped to [0, 1]
_W = 0.5 * _WEIGHTS


def left_jacobian_sim(omega: np.ndarray, lam: float) -> np.ndarray:
    """3x3 matrix ``W(ω, λ)``; ``W(ω, 0)`` is the SE(3) ``V`` matrix."""
    omega = np.asarray(omega, dtype=float)
    theta = float(np.linalg.norm(omega))
    tau = _TAU
    e = np.exp(lam * tau)
    # sin(τθ)/θ = τ·sinc(τθ/π); (1 - cos τθ)/θ² = τ²/2 · sinc(τθ/2π)²
    a = np.sum(_W * e)
    b = np.sum(_W * e * tau * np.sinc(tau * theta / np.pi))
    c = np.sum(_W * e * 0.5 * tau**2 * np.sinc(tau * theta / (2.0 * np.pi)) ** 2)
    Om = so3.hat(omega)
    return a * np.eye(3) + b * Om + c * (Om @ Om)
