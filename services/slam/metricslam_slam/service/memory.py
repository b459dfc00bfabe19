"""Give a closed SLAM session's memory back to the system.

A closed :class:`~metricslam.slam.pipeline.SlamPipeline` is cyclic garbage (the VO points back
at the pipeline, the back end's event bus at its subscribers, threads at their owners), so
reference counting alone never frees it; Python's full collection runs rarely in a process with
many long-lived objects, and measured closed sessions piled up (6 alive at once, ~20 MiB each)
before one ran. Then glibc keeps freed memory in its arenas. So after a session closes (idle
close, roll-over) the service collects and trims once: RSS levels off
(``bench/results/slam_service_soak.md``).

glibc also gives each thread that allocates its own arena (up to 8 per core): a service with a
worker, graph and depth thread per camera plus zenoh's threads spreads a session's many small
arrays over them and the free space in each stays held — the soak's RSS floor rose across
roll-overs with malloc's in-use bytes flat. :func:`limit_malloc_arenas` caps them at start.

Inside a session, the global graph's batch re-solve after each loop replaces the whole ISAM2 and
frees large temporaries whose pages stay resident until a trim: :func:`trim_heap`, called
periodically by the service, returns them between session closes. (A fixed mmap threshold would
return them at once, but cost 8-36 % more CPU at 4 MiB-128 KiB: every large array a fresh
mapping.)
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging

log = logging.getLogger(__name__)


def _glibc_function(name: str):
    """A function of the C library, or None when it is not glibc (musl, macOS) or has none."""
    lib = ctypes.util.find_library("c")
    try:
        return getattr(ctypes.CDLL(lib), name) if lib else None
    except (OSError, AttributeError):
        return None


_TRIM = _glibc_function("malloc_trim")
_M_ARENA_MAX = -8  # mallopt parameter (glibc malloc.h)


def limit_malloc_arenas(n_arenas: int) -> bool:
    """Cap glibc's malloc arenas at ``n_arenas`` (``mallopt(M_ARENA_MAX)``, what the
    ``MALLOC_ARENA_MAX`` variable sets); 0 leaves glibc's default. Call it before the threads
    start. Returns whether a cap was set (False: 0, or not glibc)."""
    if n_arenas <= 0:
        return False
    mallopt = _glibc_function("mallopt")
    return bool(mallopt is not None and mallopt(_M_ARENA_MAX, int(n_arenas)) == 1)


def trim_heap() -> None:
    """Return free heap pages to the OS (glibc only; a few ms on a 300 MB heap)."""
    if _TRIM is not None:
        _TRIM(0)


def release_memory() -> None:
    """Collect cyclic garbage, then return free heap pages to the OS (glibc only)."""
    gc.collect()
    trim_heap()
