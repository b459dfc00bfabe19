"""Conversions between our 4x4 Sim(3) arrays and ``gtsam.Similarity3``.

Ours: ``S_a_b = [[s·R, t], [0, 1]]`` maps ``p_a = s·R·p_b + t``. gtsam 4.3:
``Similarity3(R, t_g, s)`` maps ``p → s·(R·p + t_g)``, so ``t_g = t / s``. Both use tangent
``[ω, u, λ]`` (``s = e^λ``) with right perturbation. See ``docs/conventions.md``.
"""

from __future__ import annotations

import gtsam
import numpy as np

from metricslam.geometry import sim3


def to_gtsam(S_a_b: np.ndarray) -> gtsam.Similarity3:
    """4x4 ``S_a_b`` -> ``gtsam.Similarity3`` with the same action on points."""
    R, t, s = sim3.split(S_a_b)
    return gtsam.Similarity3(gtsam.Rot3(R), t / s, s)


def from_gtsam(S: gtsam.Similarity3) -> np.ndarray:
    """``gtsam.Similarity3`` -> 4x4 ``[[s·R, t], [0, 1]]`` (float64)."""
    s = float(S.scale())
    return sim3.from_rts(S.rotation().matrix(), s * np.asarray(S.translation(), dtype=float), s)


def key(kf_id: int) -> int:
    """gtsam key of keyframe ``kf_id``'s pose ``S_world_kf``: ``symbol('s', kf_id)``."""
    return gtsam.symbol("s", int(kf_id))
