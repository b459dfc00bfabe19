"""Load a :class:`~metricslam.slam.system_config.SystemConfig`: defaults → YAML → environment → flags.

The YAML file (``metricslam run --config FILE.yaml``, ``metricslam slam-service --config
FILE.yaml``, or ``METRICSLAM_CONFIG=FILE.yaml``) has up to six sections, each a mapping of
field overrides, and two top-level switches; anything left out keeps its default (the graph,
depth, queues) or the VO preset's value::

    vo:                        # 'preset' + metricslam.slam.vo.config.VOConfig fields
      preset: kitti            # default: from the dataset (run) / kitti (live service)
      keyframe_motion_px: 30
    graph:                     # metricslam.slam.graph.config.GraphConfig fields
      odom_sigma_log_scale: 0.01     # a camera whose VO drifts faster than ours
      scale_sigma_floor_log: 0.2
      loop:
        vocabulary_words: 1000
    depth:                     # DepthConfig: use_scale, model_path
      model_path: my_model.onnx
    queues:                    # QueueConfig: frames (per camera, live service)
      frames: 8
    initial_scale:             # InitialScaleConfig: enabled (live service: on), timeout_s
      timeout_s: 2.0
    scale:                     # metricslam.slam.ground.config.ScaleConfig
      sources: [learned, ground]     # default [learned]; ground needs mount_height_m
      mount_height_m: 1.65
    vo_only: false
    deterministic: false

Environment variables ``METRICSLAM_<SECTION>__<FIELD>`` (nested with ``__``) override the file,
e.g. ``METRICSLAM_GRAPH__LOOP__ENABLED=false``, ``METRICSLAM_VO__PRESET=euroc``,
``METRICSLAM_DETERMINISTIC=1``; values are read as YAML scalars. Other ``METRICSLAM_*`` names
without ``__`` belong to other tools and are left alone.

Every key is validated against the frozen configs (``extra="forbid"``): a misspelled or stale
key, a wrong type or an out-of-range value is a :class:`~metricslam.errors.ConfigError` naming it
and where it came from, before any frame is processed.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from metricslam.errors import ConfigError, validation_problems
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.ground.config import LAYER_CONTEXT
from metricslam.slam.system_config import DETERMINISTIC_GRAPH, DETERMINISTIC_VO, SystemConfig
from metricslam.slam.vo.config import VOConfig

__all__ = ["CONFIG_ENV", "DETERMINISTIC_GRAPH", "DETERMINISTIC_VO", "ENV_PREFIX", "SECTIONS",
           "ConfigOverrides", "environment_layer", "load_system_config", "read_config_file"]

#: sections (mappings) and switches (scalars) a file or the environment may set
SECTIONS = ("vo", "graph", "depth", "queues", "initial_scale", "scale")
SWITCHES = ("vo_only", "deterministic")
ENV_PREFIX = "METRICSLAM_"
#: environment variable naming the YAML file when no ``--config`` flag is given
CONFIG_ENV = "METRICSLAM_CONFIG"


def load_system_config(path: str | Path | None = None, *, env: Mapping[str, str] | None = None,
                       profile: dict[str, Any] | None = None,
                       overrides: dict[str, Any] | None = None) -> SystemConfig:
    """The :class:`SystemConfig` of one run or service, layer over layer.

    Args:
        path: YAML file; None: ``$METRICSLAM_CONFIG`` if set, else no file.
        env: environment to read ``METRICSLAM_*`` from (default ``os.environ``).
        profile: the caller's own defaults over the config classes' (e.g. ``metricslam run``'s
            offline depth queue), in the file's layout; the file overrides them.
        overrides: explicit command-line values, in the file's layout; they win over all.

    Raises:
        ConfigError: a layer is unreadable or invalid; the message names the key and the layer.
    """
    env = os.environ if env is None else env
    if path is None:
        path = env.get(CONFIG_ENV) or None
    layers = [("defaults of this command", profile or {}),
              (str(path), read_config_file(path) if path is not None else {}),
              (f"environment ({ENV_PREFIX}*)", environment_layer(env)),
              ("command line", overrides or {})]
    merged: dict[str, Any] = {}
    for where, layer in layers:
        # each layer's values are checked where they are written; rules that tie fields of
        # several layers together (``scale.sources: [ground]`` needs a mounting height, which
        # the calibration file or another layer may give) only on the combination
        _validate(layer, where, context={LAYER_CONTEXT: True})
        merged = _merge(merged, layer)
    return _validate(merged, "combined configuration")


def read_config_file(path: str | Path) -> dict[str, Any]:
    """The raw layer of a YAML file (sections checked, values not yet). Raises :class:`ConfigError`."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {p} does not exist (format: metricslam.slam.config_file)")
    try:
        raw = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML: {exc}") from exc
    allowed = set(SECTIONS) | set(SWITCHES)
    if not isinstance(raw, dict) or set(raw) - allowed:
        raise ConfigError(f"{p}: expected a mapping with sections {list(SECTIONS)} and switches "
                          f"{list(SWITCHES)}, got "
                          f"{sorted(raw) if isinstance(raw, dict) else type(raw).__name__}")
    layer: dict[str, Any] = {}
    for name, value in raw.items():
        if name in SECTIONS:
            value = value or {}
            if not isinstance(value, dict):
                raise ConfigError(f"{p}: section {name!r} must be a mapping of field: value")
        layer[name] = value
    return layer


def environment_layer(env: Mapping[str, str]) -> dict[str, Any]:
    """``METRICSLAM_<SECTION>__<FIELD>[__<FIELD>…]`` and ``METRICSLAM_<SWITCH>`` as a layer."""
    layer: dict[str, Any] = {}
    for name in sorted(env):
        if not name.startswith(ENV_PREFIX) or name == CONFIG_ENV:
            continue
        keys = name[len(ENV_PREFIX):].lower().split("__")
        if keys[0] not in SECTIONS + SWITCHES:
            if len(keys) > 1:
                raise ConfigError(f"environment variable {name}: unknown section {keys[0]!r}; "
                                  f"expected one of {list(SECTIONS)}")
            continue  # another tool's variable, e.g. METRICSLAM_SHARED_DATA
        if (keys[0] in SECTIONS) != (len(keys) > 1) or not all(keys):
            raise ConfigError(f"environment variable {name}: expected {ENV_PREFIX}<SECTION>__<FIELD> "
                              f"(sections {list(SECTIONS)}) or {ENV_PREFIX}<SWITCH> ({list(SWITCHES)})")
        node = layer
        for key in keys[:-1]:
            node = node.setdefault(key, {})
        node[keys[-1]] = _scalar(env[name])
    return layer


def _scalar(text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def _merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _validate(layer: dict[str, Any], where: str, context: dict | None = None) -> SystemConfig:
    try:
        return SystemConfig.model_validate(layer, context=context)
    except ValidationError as exc:
        raise ConfigError(f"{where}: invalid config: {validation_problems(exc)}") from exc
    except ConfigError as exc:  # raised by VOConfig inside the vo section's validator
        raise ConfigError(f"{where}: {exc}") from exc


@dataclass(frozen=True)
class ConfigOverrides:
    """Deprecated: the pre-:class:`SystemConfig` override pair, kept only until
    ``bench/landmark_depth.py`` builds its session with ``build_session``. Use
    :func:`load_system_config` and :func:`metricslam.slam.session_builder.build_session`."""

    vo: dict[str, Any] = field(default_factory=dict)
    graph: dict[str, Any] = field(default_factory=dict)

    def vo_config(self, preset: str, **fixed: Any) -> VOConfig:
        return VOConfig.preset(preset, **{**self.vo, **fixed})

    def graph_config(self, **fixed: Any) -> GraphConfig:
        try:
            return GraphConfig(**{**self.graph, **fixed})
        except ValidationError as exc:
            raise ConfigError(f"invalid graph config: {validation_problems(exc)}") from exc
