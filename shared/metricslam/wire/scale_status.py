"""The scale block of the SLAM service's status (``StatusMessage.scale_health``).

What the metric scale of one camera's session rests on and how far to trust it
(docs/ground_scale.md): the scale sources in use, the camera's mounting height, the back end's
scale uncertainty, the learned and the road-plane scale of the newest keyframe that has each,
their disagreement and the health warning, and, with learned scale only, the spread of the
per-keyframe learned scale. Every field is optional: a session without a back end or a source
leaves it out. Scales are metres per keyframe VO unit; ``*_log`` values are natural logs.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class ScaleHealthStatus(BaseModel):
    """Scale health of one camera's session (module docstring).

    Attributes:
        sources: the scale sources feeding the global graph (``learned``, ``ground``; empty:
            none, e.g. ``--no-scale``).
        mount_height_m: the camera's optical centre above the road (m); None: not given
            (learned scale only).
        scale_sigma_log: σ of the newest solved keyframe's log-scale, from the back end's
            marginal covariance (None: not solved yet or busy).
        learned_scale / ground_scale: the newest keyframe's learned (the network's robust
            estimate) and road-plane scale measurements.
        learned_spread_log: std of the last keyframes' log learned scale (the per-keyframe
            scale spread; the signal there is with learned scale only).
        disagreement_log: median ``log(learned / ground)`` over the last keyframes with both.
        warning: the sources disagree beyond ``scale.health.max_disagreement_log``.
        warnings_issued: times the warning was raised.
        ground_factors / ground_rejected: road-plane measurements accepted as factors, and not.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    sources: tuple[Literal["learned", "ground"], ...] = ()
    mount_height_m: float | None = Field(default=None, gt=0, le=10)
    scale_sigma_log: float | None = Field(default=None, ge=0)
    learned_scale: float | None = Field(default=None, gt=0)
    ground_scale: float | None = Field(default=None, gt=0)
    learned_spread_log: float | None = Field(default=None, ge=0)
    disagreement_log: float | None = None
    warning: bool = False
    warnings_issued: int = Field(default=0, ge=0)
    ground_factors: int | None = Field(default=None, ge=0)
    ground_rejected: int | None = Field(default=None, ge=0)
