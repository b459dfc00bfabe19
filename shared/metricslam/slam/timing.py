"""``TimingSummary``: count, total and maximum of a stream of durations, in constant memory.

A live session runs for hours; a list of every frame's milliseconds grows with it. Stats need
only means, per-frame totals and maxima, which this keeps exactly.
"""

from __future__ import annotations


class TimingSummary:
    """Running summary of durations in milliseconds.

    Example::

        t = TimingSummary()
        t.append(2.0); t.append(4.0)
        assert (len(t), t.total_ms, t.mean_ms, t.max_ms) == (2, 6.0, 3.0, 4.0)
    """

    __slots__ = ("count", "total_ms", "max_ms")

    def __init__(self) -> None:
        self.count = 0
        self.total_ms = 0.0
        self.max_ms = 0.0

    def append(self, ms: float) -> None:
        """Add one duration (ms); named like ``list.append`` so it replaces a list of samples."""
        self.count += 1
        self.total_ms += float(ms)
        self.max_ms = max(self.max_ms, float(ms))

    @property
    def mean_ms(self) -> float:
        """Mean duration (ms); 0.0 before any sample."""
        return self.total_ms / self.count if self.count else 0.0

    def __len__(self) -> int:
        return self.count
