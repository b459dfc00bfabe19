"""Ground-plane scale factors: a unary log-scale prior per keyframe from the road's height.

The road-height estimator (:mod:`metricslam.slam.ground`) measures the camera's height above the
road ``h_vo`` in the keyframe's VO units; with the known mounting height ``h_mount_m`` the
keyframe scale is ``s = h_mount_m / h_vo`` (metres per keyframe unit, ``S_world_kf``'s scale).
Same form as the learned factors (:mod:`.scale_factor`): a ``PriorFactorSimilarity3`` whose
measurement is the current estimate with its scale replaced by ``s`` and sigmas
``[1e4]*6 + [σ_log]`` — its λ residual is ``log(s_i / s)`` — behind its own Huber kernel, so a
keyframe whose "road" was a car or a ramp cannot pull the scale far. Frames and units:
docs/conventions.md.
"""

from __future__ import annotations

import gtsam
import numpy as np

from metricslam.errors import GraphError
from metricslam.slam.graph.scale_factor import FREE_SIGMA, with_scale


def ground_noise(sigma_log: float, huber_k: float) -> gtsam.noiseModel.Base:
    """Huber-robust diagonal noise: free on ``[ω, u]``, ``sigma_log`` on λ = log s."""
    base = gtsam.noiseModel.Diagonal.Sigmas(np.array([FREE_SIGMA] * 6 + [float(sigma_log)]))
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(float(huber_k)), base)


def make_ground_scale_factor(key: int, S_current: gtsam.Similarity3, scale: float, sigma_log: float,
                             huber_k: float) -> gtsam.PriorFactorSimilarity3:
    """One robust unary factor pulling keyframe ``key``'s scale towards ``scale`` (m per unit).

    Raises:
        GraphError: ``scale`` or ``sigma_log`` is not a positive finite number.
    """
    if not (np.isfinite(scale) and scale > 0 and np.isfinite(sigma_log) and sigma_log > 0):
        raise GraphError(f"ground scale factor needs a positive finite scale and sigma, got "
                         f"{scale!r}, {sigma_log!r}")
    return gtsam.PriorFactorSimilarity3(key, with_scale(S_current, float(scale)),
                                        ground_noise(sigma_log, huber_k))


def add_ground_scale(graph: object, kf_id: int, scale: float, sigma_log: float, huber_k: float) -> None:
    """Add keyframe ``kf_id``'s road-plane scale ``h_mount_m / h_vo`` (m per keyframe unit) to a
    :class:`~.sim3_graph.GlobalPoseGraph` as one robust log-scale factor.

    Raises:
        GraphError: unknown keyframe, or a scale or sigma that is not positive and finite.
    """
    graph.add_unary(kf_id, lambda k, S_current: make_ground_scale_factor(k, S_current, scale, sigma_log,
                                                                         huber_k), "ground")
