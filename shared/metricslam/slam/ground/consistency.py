"""``HeightConsistency``: a road height far from the recent accepted ones is not the road.

A car close ahead in the lane, a kerb or a ramp can pass the per-keyframe gates of
:mod:`.height` (raw 0013 frames 65–72: 0.7–0.9 m read for 1.65 m, behind a car). Such a
measurement is inconsistent with its neighbours along the drive, so it is refused when it is more
than ``max_deviation`` from the median of the last ``window`` accepted heights
(docs/ground_scale.md). Each keyframe's height is in its own VO units, which change when the
back end re-scales the VO, so heights are compared in the global graph's metres: ``h_vo · s_kf``
with ``s_kf`` the scale of ``S_world_kf`` now (the new keyframe's is its odometry guess, before
its own ground factor). Single-threaded, like the meter that owns it.
"""

from __future__ import annotations

import collections
import math
from typing import Callable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

#: ``kf_id -> metres per keyframe VO unit`` in the graph now (None: the keyframe is unknown)
ScaleOf = Callable[[int], "float | None"]


class HeightConsistencyConfig(BaseModel):
    """The consistency gate (``ScaleConfig.consistency``).

    Attributes:
        max_deviation: refuse a height more than this fraction from the recent median (0.25:
            on raw 0013 the accepted road heights stay within ±7 % of their running median and
            the car-ahead ones are 52–57 % under it).
        window: accepted heights the median is taken over (10, about 30 m of a car's drive).
        min_history: the gate only acts once this many accepted heights are known.
        reset_after: this many refusals in a row that agree among themselves (within
            ``max_deviation`` of their own median) replace the history: the road, not the
            history, was right (a wrong start, a changed load). 0: never.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    max_deviation: float = Field(default=0.25, gt=0)
    window: int = Field(default=10, ge=1)
    min_history: int = Field(default=3, ge=1)
    reset_after: int = Field(default=8, ge=0)


class HeightConsistency:
    """Running-median gate on accepted road heights (module docstring)."""

    def __init__(self, config: HeightConsistencyConfig | None = None) -> None:
        self.config = config or HeightConsistencyConfig()
        self._accepted: collections.deque = collections.deque(maxlen=self.config.window)  # (kf, h_vo)
        self._refused: list[tuple[int, float]] = []  # refused in a row, (kf, h_vo)

    def check(self, kf_id: int, height_vo: float, scale_of: ScaleOf | None) -> str:
        """``""`` if keyframe ``kf_id``'s height agrees with the recent accepted ones (then it is
        added to them), else why not. Without ``scale_of`` the heights are compared as given."""
        scale_of = scale_of or (lambda _k: 1.0)
        s_new = scale_of(kf_id)
        if s_new is None or not (np.isfinite(s_new) and s_new > 0):
            return ""
        recent = self._metric(self._accepted, scale_of)
        h_m = float(height_vo) * s_new
        if len(recent) < self.config.min_history:
            self._accept(kf_id, height_vo)
            return ""
        median = float(np.median(recent))
        bound = math.log1p(self.config.max_deviation)
        if abs(math.log(h_m / median)) <= bound:
            self._accept(kf_id, height_vo)
            return ""
        self._refused.append((int(kf_id), float(height_vo)))
        n = self.config.reset_after
        if n and len(self._refused) >= n:
            refused = self._metric(self._refused[-n:], scale_of)
            if len(refused) == n and np.all(np.abs(np.log(refused / np.median(refused))) <= bound):
                self._accepted.clear()
                self._accepted.extend(self._refused[-n:])
                self._refused = []
                return ""
        return (f"height {100 * (h_m / median - 1):+.0f} % from the median of the last {len(recent)} "
                f"accepted ones (a car or a kerb, not the road?)")

    def _accept(self, kf_id: int, height_vo: float) -> None:
        self._accepted.append((int(kf_id), float(height_vo)))
        self._refused = []

    @staticmethod
    def _metric(items, scale_of: ScaleOf) -> np.ndarray:
        out = []
        for kf_id, h in items:
            s = scale_of(kf_id)
            if s is not None and np.isfinite(s) and s > 0:
                out.append(h * s)
        return np.asarray(out, dtype=float)
