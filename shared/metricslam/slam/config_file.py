"""Algorithm overrides from a YAML file (``metricslam run --config FILE.yaml``).

The file has up to two sections, each a mapping of field overrides; anything left out keeps its
default (the graph) or the dataset preset's value (the VO)::

    vo:                        # metricslam.slam.vo.config.VOConfig fields
      keyframe_motion_px: 30
    graph:                     # metricslam.slam.graph.config.GraphConfig fields
      odom_sigma_log_scale: 0.01     # a camera whose VO drifts faster than ours
      scale_sigma_floor_log: 0.2
      loop:
        vocabulary_words: 1000

Every key is validated against the frozen configs (``extra="forbid"``): a misspelled or stale
key, a wrong type or an out-of-range value is a :class:`~metricslam.errors.ConfigError` that
names it, before any frame is processed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from metricslam.errors import ConfigError
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.vo.config import VOConfig

SECTIONS = ("vo", "graph")
#: what ``metricslam run --deterministic`` fixes over any file: bundle adjustment, depth and the
#: global solve run in the frame loop, so the same input gives the same trajectory byte for byte
DETERMINISTIC_VO: dict[str, Any] = {"ba_in_background": False}
DETERMINISTIC_GRAPH: dict[str, Any] = {"inline": True}


@dataclass(frozen=True)
class ConfigOverrides:
    """Validated overrides: ``vo`` and ``graph`` field dicts (possibly empty)."""

    vo: dict[str, Any] = field(default_factory=dict)
    graph: dict[str, Any] = field(default_factory=dict)

    def vo_config(self, preset: str, **fixed: Any) -> VOConfig:
        """The ``preset``'s :class:`VOConfig` with the ``vo`` overrides applied; ``fixed`` (the
        command line's) wins over the file."""
        return VOConfig.preset(preset, **{**self.vo, **fixed})

    def graph_config(self, **fixed: Any) -> GraphConfig:
        """:class:`GraphConfig` from the ``graph`` overrides; ``fixed`` (e.g. the command line's
        depth queue) wins over the file."""
        try:
            return GraphConfig(**{**self.graph, **fixed})
        except ValidationError as exc:
            raise ConfigError(f"invalid graph config: {exc}") from exc


def load_overrides(path: str | Path | None) -> ConfigOverrides:
    """Read and validate ``path`` (None: no overrides). Raises :class:`ConfigError`."""
    if path is None:
        return ConfigOverrides()
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {p} does not exist (see docs/global_graph.md for its format)")
    try:
        raw = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML: {exc}") from exc
    if not isinstance(raw, dict) or set(raw) - set(SECTIONS):
        raise ConfigError(f"{p}: expected a mapping with sections {list(SECTIONS)}, got "
                          f"{sorted(raw) if isinstance(raw, dict) else type(raw).__name__}")
    sections = {}
    for name in SECTIONS:
        section = raw.get(name) or {}
        if not isinstance(section, dict):
            raise ConfigError(f"{p}: section {name!r} must be a mapping of field: value")
        sections[name] = section
    overrides = ConfigOverrides(**sections)
    try:  # validate now, before any frame: the VO against its defaults, the graph as given
        VOConfig.from_dict(overrides.vo)
        overrides.graph_config()
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}") from exc
    return overrides
