"""``ScaleHealth``: do the scale sources agree? The user's signal that the depth network is out
of its domain (or that the road is not where the mounting height says).

It observes the back end's events — the learned :class:`~metricslam.slam.events.ScaleMeasured`
(its per-keyframe Huber estimate, as the graph uses it) and the road-plane
:class:`~metricslam.slam.events.GroundScaleMeasured` — and keeps, per keyframe, both scale
measurements (metres per keyframe VO unit) and their disagreement ``log(s_learned / s_ground)``.
When the median disagreement over the last ``ScaleHealthConfig.keyframes`` keyframes that have
both exceeds ``max_disagreement_log`` (a median: one keyframe's network error, ~6 % sd per image,
must not flip it), it logs one warning and raises the ``warning`` flag of
:meth:`ScaleHealth.snapshot` (cleared again once the median is back within half the bound). After each measurement it
stores, it emits the keyframe's record as :class:`~metricslam.slam.events.ScaleHealthUpdated` on
the bus it is attached to (the recordings log it). Thread-safe (events arrive on the depth
worker and the graph worker).
"""

from __future__ import annotations

import collections
import logging
import threading

import numpy as np

from metricslam.slam.events import GroundScaleMeasured, ScaleHealthUpdated, ScaleMeasured
from metricslam.slam.graph.scale_factor import robust_log_scale
from metricslam.slam.ground.config import ScaleHealthConfig

log = logging.getLogger(__name__)


class ScaleHealth:
    """Per-keyframe learned vs ground scale and the disagreement warning (module docstring).

    Args:
        config: the warning's bound and length.
        sigma_log, huber_k: the learned measurements' robust estimate (``GraphConfig``'s).
    """

    def __init__(self, config: ScaleHealthConfig | None = None, sigma_log: float = 0.15,
                 huber_k: float = 1.345) -> None:
        self.config = config or ScaleHealthConfig()
        self._sigma, self._k = float(sigma_log), float(huber_k)
        self._lock = threading.Lock()
        self._learned: dict[int, float] = {}  # kf_id -> m per unit
        self._ground: dict[int, float] = {}
        self._recent: collections.deque = collections.deque(maxlen=self.config.window)  # (kf, log d)
        self._done: set[int] = set()
        self._last: collections.deque = collections.deque(maxlen=self.config.keyframes)
        self._learned_recent: collections.deque = collections.deque(maxlen=self.config.window)  # log s
        self.warning = False
        self.warnings_issued = 0
        self._events = None

    def attach(self, events: object) -> None:
        """Subscribe to a back end's :class:`~metricslam.slam.events.EventBus` (and emit the
        per-keyframe records on it)."""
        self._events = events
        events.subscribe(self.on_event, ScaleMeasured, GroundScaleMeasured)

    def on_event(self, ev: object) -> None:
        if isinstance(ev, ScaleMeasured):
            if ev.error or not np.asarray(ev.scales).size:
                return
            value = float(np.exp(robust_log_scale(ev.scales, self._sigma, self._k)[0]))
            target = self._learned
        elif isinstance(ev, GroundScaleMeasured) and ev.accepted:
            value, target = float(ev.scale), self._ground
        else:
            return
        kf_id = int(ev.kf_id)
        with self._lock:
            target[kf_id] = value
            if target is self._learned:
                self._learned_recent.append(float(np.log(value)))
            self._update(kf_id)
            record = self._record(kf_id, int(ev.frame_index), int(ev.t_ns))
        if self._events is not None:
            self._events.emit(record)

    def _record(self, kf_id: int, frame_index: int, t_ns: int) -> ScaleHealthUpdated:
        """The keyframe's :class:`ScaleHealthUpdated` (caller holds ``_lock``)."""
        nan = float("nan")
        learned, ground = self._learned.get(kf_id, nan), self._ground.get(kf_id, nan)
        both = np.isfinite(learned) and np.isfinite(ground)
        spread = float(np.std(self._learned_recent)) if len(self._learned_recent) >= 2 else nan
        return ScaleHealthUpdated(kf_id, frame_index, t_ns, float(learned), float(ground),
                                  float(np.log(learned / ground)) if both else nan, bool(self.warning), spread)

    def _update(self, kf_id: int) -> None:
        if kf_id in self._done or kf_id not in self._learned or kf_id not in self._ground:
            return
        self._done.add(kf_id)
        d = float(np.log(self._learned[kf_id] / self._ground[kf_id]))
        self._recent.append((kf_id, d))
        self._last.append(d)
        median = float(np.median(self._last))
        was = self.warning
        bound = self.config.max_disagreement_log * (0.5 if was else 1.0)  # hysteresis: no flapping
        self.warning = len(self._last) == self._last.maxlen and abs(median) > bound
        if self.warning and not was:
            self.warnings_issued += 1
            log.warning("scale sources disagree: the learned scale is %+.0f %% off the road plane's "
                        "(median of the last %d keyframes, up to keyframe %d); the depth network may "
                        "be out of its domain, or the mounting height or the road may be wrong "
                        "(docs/ground_scale.md)", 100 * (np.exp(median) - 1), len(self._last), kf_id)

    def snapshot(self) -> dict:
        """What the status and ``run --json`` report: the last keyframes' learned and ground
        scales, the disagreement (log) and its median, the learned scale's spread, the flag."""
        with self._lock:
            recent = list(self._recent)
            last = sorted(set(self._learned) | set(self._ground))[-self.config.window:]
            learned = np.log([self._learned[k] for k in last if k in self._learned])
        return {
            "warning": bool(self.warning), "warnings_issued": int(self.warnings_issued),
            "disagreement_log_last": float(np.median(self._last)) if self._last else None,
            "disagreement_log_median": float(np.median([d for _, d in recent])) if recent else None,
            "learned_spread_log": float(np.std(learned)) if learned.size >= 2 else None,
            "keyframes": [{"kf_id": int(k), "learned": self._learned.get(k), "ground": self._ground.get(k)}
                          for k in last],
        }
