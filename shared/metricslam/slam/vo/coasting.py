"""Where a camera went while the VO had lost track of it: the motion of its last tracked frames,
kept through the loss (:class:`MotionMemory`, used by :class:`~metricslam.slam.vo.local_vo.LocalVO`).

After a tracking loss the VO re-initializes and starts a new segment. It starts where the mean
motion of the last :data:`COAST_STEPS` tracked frames (a twist per nanosecond), kept up for the
time since the last of them (at most ``coast_max_s``), takes the camera, and the baseline of
its re-initialization is the distance covered per frame at the loss times the frames between
its two views, so the new segment keeps the lost one's units (metres once the global graph's
warps made them so). Rule and numbers: ``docs/history/rule_tracking_loss_session18.md``,
``bench/results/tracking_loss.md``.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from metricslam.geometry import se3
from metricslam.slam.vo.ba import orthonormalized

#: tracked steps whose mean motion a lost camera is taken to keep
COAST_STEPS = 5


class MotionMemory:
    """The last tracked steps of one camera, and what was kept of them at its last loss.

    Args:
        max_s: the longest time (s) the motion at a loss is kept up (``coast_max_s``; 0: never).
    """

    def __init__(self, max_s: float) -> None:
        self.max_s = float(max_s)
        self.step_at_loss = 0.0  # distance per frame (VO units) at the last loss
        self._steps: deque = deque(maxlen=COAST_STEPS)  # (twist (6,) per ns, t_ns)
        self._t_last_ns: int | None = None  # time of the newest tracked frame
        self._kept: tuple[np.ndarray, int] | None = None  # (mean twist (6,) per ns, t_ns) at the loss

    def tracked(self, T_last_cur: np.ndarray, t_ns: int) -> None:
        """A frame at ``t_ns`` was tracked, ``T_last_cur`` (4, 4) from the previous tracked one."""
        if self._t_last_ns is not None and t_ns > self._t_last_ns:
            self._steps.append((se3.log(orthonormalized(T_last_cur)) / (t_ns - self._t_last_ns), int(t_ns)))
        self._t_last_ns = int(t_ns)

    def started(self, t_ns: int) -> None:
        """A new segment was initialized at ``t_ns``: its steps count from there."""
        self._t_last_ns = int(t_ns)

    def lost(self, T_last_cur: np.ndarray) -> None:
        """Tracking was lost; ``T_last_cur`` (4, 4) is the last tracked step."""
        self.step_at_loss = float(np.linalg.norm(np.asarray(T_last_cur)[:3, 3]))
        self._kept = (np.mean([w for w, _ in self._steps], axis=0), self._steps[-1][1]) if self._steps else None
        self._steps.clear()
        self._t_last_ns = None

    def warp(self, s: float) -> None:
        """The VO's units were scaled by ``s`` (a global-graph warp)."""
        k = np.r_[np.ones(3), np.full(3, s)]
        self.step_at_loss *= s
        self._steps = deque(((w * k, t) for w, t in self._steps), maxlen=COAST_STEPS)
        if self._kept is not None:
            self._kept = (self._kept[0] * k, self._kept[1])

    def pose_at(self, T_world_last: np.ndarray, t_ns: int) -> np.ndarray:
        """Where the camera last tracked at ``T_world_last`` (4, 4) is at ``t_ns`` after the
        loss; ``T_world_last`` itself before any loss, or when the time since is not positive or
        longer than ``max_s`` (constant velocity means nothing then)."""
        if self._kept is None or not 0 < t_ns - self._kept[1] <= self.max_s * 1e9:
            return np.array(T_world_last, dtype=float)
        return T_world_last @ se3.exp((t_ns - self._kept[1]) * self._kept[0])
