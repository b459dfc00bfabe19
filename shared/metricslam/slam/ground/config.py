"""``ScaleConfig``: which scale sources feed the global graph, the camera's mounting height, and
the ground-plane factor's and the scale-health signal's parameters (``SystemConfig.scale``).

``sources``: ``[learned]`` (default: the paper's learned scale factors only; unchanged byte for
byte), ``[ground]`` (road-plane height only; needs ``mount_height_m``) or ``[learned, ground]``.
On the command line ``--scale-sources learned,ground`` and ``--mount-height 1.65``; in a config
file the ``scale:`` section. See docs/ground_scale.md.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from metricslam.errors import ConfigError
from metricslam.slam.ground.consistency import HeightConsistencyConfig
from metricslam.slam.ground.height import GroundHeightConfig

ScaleSource = Literal["learned", "ground"]

#: the largest mounting height accepted (m): above it the value is almost surely a unit mistake
MAX_MOUNT_HEIGHT_M = 10.0
#: validation-context key: the values are ONE layer of a configuration (file, environment,
#: command line); rules that need fields of other layers wait for the combination
#: (:func:`metricslam.slam.config_file.load_system_config`)
LAYER_CONTEXT = "one_layer"


def check_mount_height(h_mount_m: float | None, where: str = "mount height") -> float | None:
    """``h_mount_m`` if it is a plausible height above the road (0 < h ≤ 10 m, finite) or None;
    else :class:`~metricslam.errors.ConfigError` saying what to fix."""
    if h_mount_m is None:
        return None
    try:
        h = float(h_mount_m)
    except (TypeError, ValueError):
        raise ConfigError(f"{where + ': ' if where else ''}expected metres above the road as a number, got "
                          f"{h_mount_m!r}") from None
    if not math.isfinite(h) or h <= 0 or h > MAX_MOUNT_HEIGHT_M:
        raise ConfigError(f"{where + ': ' if where else ''}{h_mount_m!r} m is not a camera height above the "
                          f"road; give the optical centre's height in metres, 0 < h <= {MAX_MOUNT_HEIGHT_M:g} "
                          f"(KITTI's cam 0: 1.65)")
    return h


def parse_scale_sources(text: str) -> tuple[str, ...]:
    """``"learned,ground"`` → ``("learned", "ground")`` (the ``--scale-sources`` option)."""
    names = tuple(s.strip() for s in str(text).split(",") if s.strip())
    bad = [s for s in names if s not in ("learned", "ground")]
    if not names or bad or len(set(names)) != len(names):
        raise ConfigError(f"--scale-sources {text!r}: expected a comma-separated subset of "
                          f"learned,ground without repeats (e.g. learned,ground)")
    return names


class ScaleHealthConfig(BaseModel):
    """When the scale sources disagree enough to warn (docs/ground_scale.md).

    Attributes:
        max_disagreement_log: the median |log(s_learned / s_ground)| over the last
            ``keyframes`` keyframes above which the sources disagree (0.15 ≈ 16 %: about 2.5x the
            network's documented per-image error, 0.053-0.059, so a healthy network rarely
            trips it).
        keyframes: keyframes with both measurements the median is taken over: 15, about the
            network error's correlation length along the road (11-14 keyframes,
            ``GraphConfig.scale_sigma_floor_log``), so the median spans independent images.
        window: keyframes the learned-only spread is computed over.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    max_disagreement_log: float = Field(default=0.15, gt=0)
    keyframes: int = Field(default=15, ge=1)
    window: int = Field(default=20, ge=2)


class ScaleConfig(BaseModel):
    """Scale sources of the global graph (module docstring).

    Attributes:
        sources: ``["learned"]``, ``["ground"]`` or ``["learned", "ground"]``.
        mount_height_m: camera optical centre above the road (m); None = unknown.
        ground: the road-height estimator (:class:`GroundHeightConfig`).
        ground_sigma_log: sigma of one keyframe's ground log-scale factor. Larger than the
            estimator's own σ: it is correlated along the road (car pitch, road camber).
        ground_huber_k: Huber threshold on the whitened ground residual.
        consistency: the gate against the recent accepted heights (:class:`HeightConsistencyConfig`).
        health: the disagreement warning (:class:`ScaleHealthConfig`).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    sources: tuple[ScaleSource, ...] = ("learned",)
    mount_height_m: float | None = None
    ground: GroundHeightConfig = GroundHeightConfig()
    ground_sigma_log: float = Field(default=0.05, gt=0)
    ground_huber_k: float = Field(default=1.345, gt=0)
    consistency: HeightConsistencyConfig = HeightConsistencyConfig()
    health: ScaleHealthConfig = ScaleHealthConfig()

    @field_validator("sources", mode="before")
    @classmethod
    def _sources(cls, value: object) -> object:
        if isinstance(value, str):
            return parse_scale_sources(value)
        if isinstance(value, (list, tuple)) and len(set(value)) != len(value):
            raise ValueError(f"scale sources repeat: {list(value)}")
        return value

    @field_validator("mount_height_m")
    @classmethod
    def _height(cls, value: float | None) -> float | None:
        try:
            return check_mount_height(value, "")  # pydantic names the field and the layer
        except ConfigError as exc:
            raise ValueError(str(exc)) from None

    @model_validator(mode="after")
    def _ground_needs_height(self, info: ValidationInfo) -> "ScaleConfig":
        if not self.sources:
            raise ValueError("scale.sources is empty; use learned, ground or both")
        one_layer = bool(info.context and info.context.get(LAYER_CONTEXT))  # the height may be in another
        if "ground" in self.sources and self.mount_height_m is None and not one_layer:
            raise ValueError("scale source 'ground' needs the camera's mounting height: give "
                             "--mount-height M, mount_height_m in the calibration file or "
                             "scale.mount_height_m in the config")
        return self

    @property
    def learned(self) -> bool:
        return "learned" in self.sources

    @property
    def ground_on(self) -> bool:
        return "ground" in self.sources
