"""Give a closed SLAM session's memory back to the system.

A closed :class:`~metricslam.slam.pipeline.SlamPipeline` is cyclic garbage (the VO points back
at the pipeline, the back end's event bus at its subscribers, threads at their owners), so
reference counting alone never frees it; Python's full collection runs rarely in a process with
many long-lived objects, and measured closed sessions piled up (6 alive at once, ~20 MiB each)
before one ran. Then glibc keeps freed memory in its arenas. So after a session closes (idle
close, roll-over) the service collects and trims once: RSS levels off
(``bench/results/slam_service_soak.md``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging

log = logging.getLogger(__name__)


def _malloc_trim():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to trim
        return None


_TRIM = _malloc_trim()


def release_memory() -> None:
    """Collect cyclic garbage, then return free heap pages to the OS (glibc only)."""
    gc.collect()
    if _TRIM is not None:
        _TRIM(0)
