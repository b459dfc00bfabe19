"""``SystemConfig``: the one frozen configuration a running SLAM system is built from.

It composes the per-module configs — each stays the owner of its own defaults — and adds only
what none of them owns::

    SystemConfig
      vo:            VOSelection   preset name + VOConfig field overrides (VOConfig owns the values)
      graph:         GraphConfig   global Sim(3) graph, loop closure (graph.loop), depth request queue
      depth:         DepthConfig   learned scale on/off, in-process ONNX model
      queues:        QueueConfig   frames buffered per camera in the live service
      initial_scale: InitialScaleConfig  provisional metric scale at VO initialization (live)
      scale:         ScaleConfig   scale sources (learned, ground), mounting height, scale health
      vo_only:       bool          local VO only, no global graph (implies no learned scale)
      deterministic: bool          BA, depth and the global solve in the frame loop

Loaded by :func:`metricslam.slam.config_file.load_system_config` in the order defaults → YAML
file (``--config``) → ``METRICSLAM_*`` environment → command-line flags, and turned into a
running session by :func:`metricslam.slam.session_builder.build_session`. Every model is frozen
with ``extra="forbid"``: a stale or misspelled key is an error that names it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.ground.config import ScaleConfig
from metricslam.slam.initial_scale import InitialScaleConfig
from metricslam.slam.vo.config import PresetName, VOConfig

#: VO preset of a live session when neither the config nor the caller names one
DEFAULT_PRESET: PresetName = "kitti"
#: what ``deterministic`` fixes over any file or environment: bundle adjustment, depth and the
#: global solve run in the frame loop, so the same input gives the same trajectory byte for byte
DETERMINISTIC_VO: dict[str, Any] = {"ba_in_background": False}
DETERMINISTIC_GRAPH: dict[str, Any] = {"inline": True}
#: the live SLAM service's defaults over the classes' (a profile of
#: :func:`~metricslam.slam.config_file.load_system_config`; a file, the environment or flags still
#: override it): poses are published as they are made, so the first one should already be metric
#: (:mod:`metricslam.slam.initial_scale`). Offline ``metricslam run`` keeps the class defaults, so
#: its (deterministic) trajectories do not change.
LIVE_PROFILE: dict[str, Any] = {"initial_scale": {"enabled": True}}


class VOSelection(BaseModel):
    """Which VO parameters: a preset of :class:`VOConfig` plus field overrides.

    In a YAML file or the environment this is the flat ``vo:`` section — ``preset`` plus any
    :class:`VOConfig` field (``vo: {preset: kitti, keyframe_motion_px: 30}``).

    Attributes:
        preset: ``kitti``, ``euroc``, ``tum`` or ``synth``; None lets the caller choose (``run``:
            from the dataset's format; the live service: :data:`DEFAULT_PRESET`).
        overrides: :class:`VOConfig` fields that replace the preset's values.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    preset: PresetName | None = None
    overrides: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="before")
    @classmethod
    def _from_flat_section(cls, data: Any) -> Any:
        if isinstance(data, dict) and "overrides" not in data:
            fields = dict(data)
            preset = fields.pop("preset", None)
            return {"preset": preset, "overrides": fields}
        return data

    @model_validator(mode="after")
    def _check_overrides(self) -> "VOSelection":
        VOConfig.from_dict(self.overrides)  # names a misspelled key, a wrong type, a bad value
        return self


class DepthConfig(BaseModel):
    """Learned scale factors and where their depth comes from inside the process.

    Attributes:
        use_scale: add learned scale factors (False: the ``--no-scale`` baseline — same graph and
            loops, no depth source is created or called, output in the VO's arbitrary scale).
        model_path: ONNX depth model of the in-process source (None: the shipped int8 model).
            Not used when the caller passes its own depth source (the live service's HTTP
            client of the depth service).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    use_scale: bool = True
    model_path: Path | None = None


class QueueConfig(BaseModel):
    """Bounded queues of the live system; when one is full its OLDEST entry is dropped and counted.

    The depth-request queue of the global graph is ``graph.depth_queue_size`` (its owner).

    Attributes:
        frames: frames buffered per camera by the SLAM service before its session.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    frames: int = Field(default=8, ge=1, le=10_000)


class SystemConfig(BaseModel):
    """Everything :func:`~metricslam.slam.session_builder.build_session` needs (module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    vo: VOSelection = VOSelection()
    graph: GraphConfig = GraphConfig()
    depth: DepthConfig = DepthConfig()
    queues: QueueConfig = QueueConfig()
    initial_scale: InitialScaleConfig = InitialScaleConfig()
    scale: ScaleConfig = ScaleConfig()
    vo_only: bool = False
    deterministic: bool = False

    @property
    def use_scale(self) -> bool:
        """Learned scale factors take part (on, a scale source, and a global graph to put them in)."""
        return self.depth.use_scale and self.scale.learned and not self.vo_only

    @property
    def use_ground(self) -> bool:
        """Ground-plane scale factors take part (``scale.sources`` has ground, and a graph)."""
        return self.scale.ground_on and not self.vo_only

    @property
    def mode(self) -> str:
        """``metric``, ``no-scale`` or ``vo-only`` (run statistics, logs)."""
        if self.vo_only:
            return "vo-only"
        return "metric" if self.use_scale or self.use_ground else "no-scale"

    def vo_config(self, default_preset: str = DEFAULT_PRESET) -> VOConfig:
        """The resolved :class:`VOConfig`: ``vo.preset`` (else ``default_preset``) with
        ``vo.overrides``; in deterministic mode :data:`DETERMINISTIC_VO` wins over both."""
        fixed = DETERMINISTIC_VO if self.deterministic else {}
        return VOConfig.preset(self.vo.preset or default_preset, **{**self.vo.overrides, **fixed})

    def graph_config(self) -> GraphConfig:
        """The resolved :class:`GraphConfig`; deterministic mode fixes :data:`DETERMINISTIC_GRAPH`."""
        if not self.deterministic:
            return self.graph
        return GraphConfig(**{**self.graph.model_dump(), **DETERMINISTIC_GRAPH})
