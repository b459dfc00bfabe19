"""A session's scale health for its status (:class:`~metricslam.wire.scale_status.ScaleHealthStatus`)
from its ``stats()`` (:meth:`metricslam.slam.pipeline.SlamPipeline.stats`: ``scale`` and the back
end's ``scale_health`` / ``scale_sigma_log`` / ground counters; docs/ground_scale.md)."""

from __future__ import annotations

import math

from metricslam.wire.scale_status import ScaleHealthStatus


def _positive(value: object) -> float | None:
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) and value > 0 else None


def _finite(value: object) -> float | None:
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def scale_health_status(stats: dict) -> ScaleHealthStatus | None:
    """The status block, or None when the session reports no scale (identity sessions)."""
    scale = stats.get("scale")
    if not isinstance(scale, dict):
        return None
    backend = stats.get("backend") or {}
    health = backend.get("scale_health") or {}
    newest: dict[str, float | None] = {"learned": None, "ground": None}
    for kf in health.get("keyframes") or []:  # oldest first: the newest with a value wins
        for name in newest:
            if _positive(kf.get(name)) is not None:
                newest[name] = _positive(kf.get(name))
    sigma = _finite(backend.get("scale_sigma_log"))
    spread = _finite(health.get("learned_spread_log"))
    ground = "ground" in scale.get("sources", ())
    return ScaleHealthStatus(
        sources=tuple(scale.get("sources", ())), mount_height_m=_positive(scale.get("mount_height_m")),
        scale_sigma_log=None if sigma is None else abs(sigma), learned_scale=newest["learned"],
        ground_scale=newest["ground"], learned_spread_log=None if spread is None else abs(spread),
        disagreement_log=_finite(health.get("disagreement_log_last")),
        warning=bool(health.get("warning", False)), warnings_issued=int(health.get("warnings_issued") or 0),
        ground_factors=int(backend.get("ground_factors", 0)) if ground else None,
        ground_rejected=(int(backend.get("ground_measured", 0)) - int(backend.get("ground_accepted", 0))
                         if ground else None))
