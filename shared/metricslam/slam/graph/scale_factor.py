"""Learned scale factors (paper eq. 12) as gtsam C++ factors.

For landmark ``j`` of keyframe ``i`` the VO inverse depth ``ξ_j`` (1 / keyframe units) and the
network's metric inverse depth ``z_j`` (1/m) at the landmark's pixel measure the keyframe scale
``s_i = ξ_j / z_j`` (metres per keyframe unit; ``S_world_kf``'s scale). We use it in log form: a
``PriorFactorSimilarity3`` whose measurement is the current estimate with its scale replaced by
``s_j`` and sigmas ``[1e4]*6 + [σ_log_s]`` — the λ component of ``Log(S_prior⁻¹ S)`` is exactly
``log(s / s_j)``, the other six are ~0 and carry ~no weight — behind a Huber kernel (ε_s).
DESIGN.md measured this at 3–7 ms where Python ``CustomFactor``s were ~15x slower.

Two modes (``GraphConfig.scale_factor_mode``):

* ``"per_landmark"`` — eq. 13 literally: one Huber factor per landmark.
* ``"per_keyframe"`` (default) — the landmark factors of keyframe ``i`` touch only ``s_i``, so
  their sum is a 1-D robust cost in ``log s_i``; we minimize it in numpy (Huber IRLS, same σ and
  ε_s) and add ONE Gaussian factor at the M-estimate with its curvature ``Σ w_j / σ²`` (sigma
  floored at ``scale_sigma_floor_log``: the network errs per image, not per landmark). At the
  joint optimum this differs only through where the Huber weights are evaluated; it keeps the
  graph at one scale factor per keyframe (48x fewer factors), which is what keeps ISAM2's
  per-keyframe cost flat at 10,000 keyframes (``bench/results/graph_scaling.md``).
"""

from __future__ import annotations

import gtsam
import numpy as np

from metricslam.slam.graph.config import GraphConfig

#: sigma of the six non-scale components: "no information" without breaking positive-definiteness.
FREE_SIGMA = 1e4


def scale_measurements(
    landmarks_inv_depth: np.ndarray, net_inv_depth_per_m: np.ndarray, config: GraphConfig
) -> np.ndarray:
    """Per-landmark scale measurements ``s_j = ξ_j / z_j`` (K,), unusable ones removed.

    Args:
        landmarks_inv_depth: (M,) VO inverse depths ξ_j (1 / keyframe units).
        net_inv_depth_per_m: (M,) network inverse depth z_j (1/m) sampled at the landmarks.
        config: inverse depths outside ``[min_inv_depth_per_m, max_inv_depth_per_m]``
            (sky / too near) and non-finite values are dropped; with ``scale_max_depth_m`` the
            range gate (:func:`range_gate`) applies; at most ``max_scale_landmarks`` are kept
            (even subsample, deterministic).
    """
    xi = np.asarray(landmarks_inv_depth, dtype=float).reshape(-1)
    z = np.asarray(net_inv_depth_per_m, dtype=float).reshape(-1)
    ok = (
        np.isfinite(xi) & np.isfinite(z) & (xi > 0)
        & (z >= config.min_inv_depth_per_m) & (z <= config.max_inv_depth_per_m)
    )
    s = xi[ok] / z[ok]
    if config.scale_max_depth_m is not None and s.size:
        s = s[range_gate(xi[ok], s, config.scale_max_depth_m, config.scale_gate_min_landmarks)]
    if s.size > config.max_scale_landmarks:
        idx = np.linspace(0, s.size - 1, config.max_scale_landmarks).round().astype(int)
        s = s[idx]
    return s


def range_gate(xi: np.ndarray, scales: np.ndarray, max_depth_m: float, min_keep: int,
               iterations: int = 5) -> np.ndarray:
    """(K,) bool: the landmarks within ``max_depth_m`` of the camera by the keyframe's own scale.

    A landmark's metric depth is ``s / ξ_j`` for the keyframe scale ``s`` (m per VO unit); ``s``
    starts as the median of all measurements and is re-estimated from the kept ones until the
    selection stops changing — the VO's *relative* depths are exact, so only the common scale
    is uncertain. When fewer than ``min_keep`` are within range, the ``min_keep`` nearest (largest
    ``ξ``) are kept instead, so a keyframe that sees only far structure still gets a measurement.
    """
    xi = np.asarray(xi, dtype=float)
    scales = np.asarray(scales, dtype=float)
    if scales.size <= min_keep:
        return np.ones(scales.size, dtype=bool)
    nearest = np.zeros(scales.size, dtype=bool)
    nearest[np.argsort(-xi, kind="stable")[:min_keep]] = True
    keep = np.ones(scales.size, dtype=bool)
    for _ in range(iterations):
        within = float(np.median(scales[keep])) / xi <= max_depth_m
        new = within if within.sum() >= min_keep else nearest
        if np.array_equal(new, keep):
            break
        keep = new
    return keep


def robust_log_scale(scales: np.ndarray, sigma_log: float, huber_k: float,
                     iterations: int = 20) -> tuple[float, float]:
    """Huber M-estimate of ``log s`` from per-landmark measurements (IRLS from the median).

    Returns:
        ``(log_s_hat, sigma_eff)`` with ``sigma_eff = σ / sqrt(Σ w_j)`` (the curvature of the
        summed Huber cost at the estimate). Raises ``ValueError`` for an empty input.
    """
    x = np.log(np.asarray(scales, dtype=float).reshape(-1))
    x = x[np.isfinite(x)]
    if x.size == 0:
        raise ValueError("no finite scale measurements")
    mu = float(np.median(x))
    w = np.ones_like(x)
    for _ in range(iterations):
        r = np.abs(x - mu) / sigma_log
        w = np.where(r <= huber_k, 1.0, huber_k / np.maximum(r, 1e-12))
        mu_new = float(np.sum(w * x) / np.sum(w))
        if abs(mu_new - mu) < 1e-9:
            mu = mu_new
            break
        mu = mu_new
    r = np.abs(x - mu) / sigma_log
    w_quad = (r <= huber_k).astype(float)  # curvature: only the quadratic part contributes
    info = max(float(np.sum(w_quad)), 1.0)
    return mu, sigma_log / float(np.sqrt(info))


def make_keyframe_scale_factor(key: int, S_current: gtsam.Similarity3, scales: np.ndarray,
                               config: GraphConfig) -> gtsam.PriorFactorSimilarity3:
    """One Gaussian log-scale factor summarizing a keyframe's landmark measurements."""
    log_s, sigma_eff = robust_log_scale(scales, config.scale_sigma_log, config.scale_huber_k)
    sigma_eff = max(sigma_eff, config.scale_sigma_floor_log)  # the image's error, not the landmarks'
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([FREE_SIGMA] * 6 + [sigma_eff]))
    return gtsam.PriorFactorSimilarity3(key, with_scale(S_current, float(np.exp(log_s))), noise)


def scale_noise(config: GraphConfig) -> gtsam.noiseModel.Base:
    """Huber-robust diagonal noise: free on ``[ω, u]``, ``σ_log_s`` on λ."""
    base = gtsam.noiseModel.Diagonal.Sigmas(np.array([FREE_SIGMA] * 6 + [config.scale_sigma_log]))
    return gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(config.scale_huber_k), base
    )


def with_scale(S: gtsam.Similarity3, s_new: float) -> gtsam.Similarity3:
    """``S ∘ Exp([0,…,0, log(s_new / s)])``: same rotation and origin, scale ``s_new``."""
    zeta = np.zeros(7)
    zeta[6] = np.log(float(s_new) / float(S.scale()))
    return S.compose(gtsam.Similarity3.Expmap(zeta))


def make_scale_factors(
    key: int, S_current: gtsam.Similarity3, scales: np.ndarray, noise: gtsam.noiseModel.Base
) -> list[gtsam.PriorFactorSimilarity3]:
    """One unary factor per scale measurement on keyframe ``key``."""
    return [gtsam.PriorFactorSimilarity3(key, with_scale(S_current, float(s)), noise) for s in scales]


def log_scale_residual(S_prior: gtsam.Similarity3, S: gtsam.Similarity3) -> float:
    """The λ component of ``Log(S_prior⁻¹ S)`` (= ``log(s / s_prior)``)."""
    return float(gtsam.Similarity3.Logmap(S_prior.inverse().compose(S))[6])


def marginal_sigma_log(isam: gtsam.ISAM2, key: int) -> float | None:
    """σ of ``log s`` of the Similarity3 variable ``key`` from ISAM2's marginal covariance
    (tangent ``[ω, u, λ]``: λ = log s is the last); None when the marginal fails."""
    try:
        return float(np.sqrt(max(isam.marginalCovariance(key)[6, 6], 0.0)))
    except (RuntimeError, IndexError):  # indeterminate: no answer rather than a wrong one
        return None
