"""Suspect frames: tracks that may be aliased on repeating texture (``docs/vo.md``).

On a grid of windows, a KLT start one period off (the constant-velocity guess where a turn starts
or ends) makes most tracks converge one period away, all agreeing with each other: neither the
forward-backward check nor the essential-matrix RANSAC can tell, and the pose follows them for
several frames. What shows is the share of a frame's tracks the essential check rejects (the
wrong tracks and the right ones disagree). A tracked frame is *suspect* when that share is above
``VOConfig.suspect_reject_share`` on it and on the tracked frame before it
(``docs/history/rule_vo_aliasing_report_session21.md``).

Before that, a frame whose share is above ``VOConfig.retrack_reject_share`` is tracked again from
the global image shift instead of the motion guess (:func:`retrack`), and that set is kept only
when it is decisively more consistent (``docs/history/rule_vo_retrack2_session21.md``); the
report reads the kept set's share.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    import numpy as np

    from metricslam.slam.vo.frontend import KLTFrontend


class SuspectFrames:
    """Counts suspect frames and keeps their ``[first, last]`` frame-index ranges.

    Args:
        threshold: the rejected share above which a frame is *high* (two in a row: suspect).
        max_ranges: ranges kept (a long live session keeps counting beyond them).
    """

    def __init__(self, threshold: float, max_ranges: int = 1000) -> None:
        self.threshold = threshold
        self.max_ranges = max_ranges
        self.count = 0
        self.ranges: list[list[int]] = []
        self._previous_high = False

    def update(self, frame_index: int, rejected_share: float) -> bool:
        """Record one tracked frame's rejected share (0..1); True when the frame is suspect."""
        high = rejected_share > self.threshold
        suspect = high and self._previous_high
        self._previous_high = high
        if suspect:
            self.count += 1
            if self.ranges and self.ranges[-1][1] == frame_index - 1:
                self.ranges[-1][1] = frame_index
            elif len(self.ranges) < self.max_ranges:
                self.ranges.append([frame_index, frame_index])
        return suspect

    def mark(self, first: int, last: int) -> None:
        """Frames ``first..last``, none before the newest range's first, are suspect for another
        reason (a two-view start the frames between its views do not confirm)."""
        if self.ranges and first <= self.ranges[-1][1] + 1:
            end = self.ranges[-1][1]
            self.count += max(last - end, 0)
            self.ranges[-1][1] = max(end, last)
            return
        self.count += last - first + 1
        if len(self.ranges) < self.max_ranges:
            self.ranges.append([first, last])

    def interrupt(self) -> None:
        """Tracking stopped (a loss): the next tracked frame has no predecessor to agree with."""
        self._previous_high = False


def describe_ranges(ranges: list[list[int]]) -> str:
    """``"108-117, 130"``: :attr:`SuspectFrames.ranges` (or ``vo_suspect_ranges``) for messages."""
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in ranges)


def retrack(frontend: KLTFrontend, gray: np.ndarray, rejected_share: float, check: Callable[[], float],
            counters: dict[str, int]) -> float:
    """Track the frame ``gray`` ((H, W) uint8) again (:meth:`KLTFrontend.retrack`) after ``check`` (drop tracks
    without a landmark and the essential check's rejects; returns the rejected share) rejected
    ``rejected_share`` of the first set. The new set is kept when ``check`` rejects less than half
    that share of it and at least as many tracks survive; else the first set is restored.
    Counts ``retracks`` and ``retracks_kept`` in ``counters``; returns the kept set's share."""
    first = frontend.tracks
    counters["retracks"] += 1
    frontend.retrack(gray)
    share = check()
    if share < rejected_share / 2 and len(frontend.ids) >= len(first):
        counters["retracks_kept"] += 1
        return share
    frontend.restore(first)
    return rejected_share
