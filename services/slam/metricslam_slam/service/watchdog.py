"""The SLAM service's own liveness watchdog: a hung service ends its process, so that whatever
started it restarts it.

Docker Compose never restarts a container for failing its health check, only one whose process
exited (``restart: unless-stopped``); Kubernetes restarts on a failed liveness probe. Both are
served from inside the process, without a sidecar or an "autoheal" container with the Docker
socket:

* every ``period_s`` a thread checks that the status loop still ticks and that no camera worker
  has been stuck on one frame for ``hang_timeout_s`` (a deadlock, a native call that never
  returns). When something has, it logs what and exits the process with :data:`EXIT_HUNG`
  (``os._exit``: a hung thread would block an orderly shutdown). Each camera's trajectory is
  already on disk pose by pose (``SLAM_STATE_DIR``), so the restarted service continues it.
* while all is well it rewrites ``heartbeat_file`` (if set). A process frozen as a whole (SIGSTOP,
  a native call holding the GIL) cannot run this thread either; the file then goes stale, which
  is what ``python -m metricslam_slam.supervisor.healthcheck --alive`` (the Kubernetes liveness
  probe) checks. It reads no network, so a router outage never restarts the SLAM service.

The router is not watched here: frames not arriving is not a hang.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path

log = logging.getLogger(__name__)

#: exit status of a process the watchdog ended (EX_SOFTWARE)
EXIT_HUNG = 70


def write_heartbeat(path: Path, now_s: float | None = None) -> None:
    """Replace ``path`` with the wall-clock time (seconds) atomically (never half-written)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(f"{time.time() if now_s is None else now_s:.3f}\n")
    os.replace(tmp, path)


def heartbeat_age_s(path: Path, now_s: float | None = None) -> float | None:
    """Seconds since the heartbeat in ``path`` was written; None if there is none (yet)."""
    try:
        written = float(path.read_text().strip())
    except (OSError, ValueError):
        return None
    return (time.time() if now_s is None else now_s) - written


class Watchdog:
    """Checks the service's loops every ``period_s`` on its own daemon thread.

    Args:
        hang_timeout_s: how long a loop may make no progress before the process is ended.
        stalls: returns ``(what, seconds without progress)`` for each watched loop, e.g.
            ``("camera cam0", 3.2)``; seconds are monotonic.
        heartbeat_file: rewritten after each check that found nothing hung; None: no file.
        period_s: how often to check (default: a quarter of the timeout, at most 5 s).
        on_hang: what to do with the message (default: log it and ``os._exit(EXIT_HUNG)``).
    """

    def __init__(self, hang_timeout_s: float, stalls: Callable[[], Iterable[tuple[str, float]]],
                 heartbeat_file: Path | None = None, period_s: float | None = None,
                 on_hang: Callable[[str], None] | None = None) -> None:
        self.hang_timeout_s = hang_timeout_s
        self.period_s = period_s if period_s is not None else min(5.0, hang_timeout_s / 4)
        self._stalls = stalls
        self.heartbeat_file = heartbeat_file
        self._on_hang = on_hang or _exit_hung
        self._stop = threading.Event()
        # not "slam-…": that prefix names camera workers (the service and its tests count them)
        self._thread = threading.Thread(target=self._run, name="service-watchdog", daemon=True)

    def start(self) -> "Watchdog":
        if self.heartbeat_file is not None:
            self.heartbeat_file.parent.mkdir(parents=True, exist_ok=True)
            write_heartbeat(self.heartbeat_file)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(self.period_s + 1.0)

    def check(self) -> str | None:
        """One check: the message naming what is hung, or None (and the heartbeat written)."""
        hung = [(what, s) for what, s in self._stalls() if s > self.hang_timeout_s]
        if hung:
            return ("hung: " + "; ".join(f"{what} made no progress for {s:.0f} s" for what, s in hung)
                    + f" (SLAM_HANG_TIMEOUT_S={self.hang_timeout_s:g})")
        if self.heartbeat_file is not None:
            try:
                write_heartbeat(self.heartbeat_file)
            except OSError as exc:  # a full disk must not look like a hang to the watchdog itself
                log.warning("cannot write the heartbeat file %s: %s", self.heartbeat_file, exc)
        return None

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            message = self.check()
            if message is not None:
                self._on_hang(message)
                return


def _exit_hung(message: str) -> None:
    log.critical("%s; ending the process (exit %d) so that it is restarted", message, EXIT_HUNG)
    for handler in logging.getLogger().handlers:
        handler.flush()
    sys.stderr.flush()
    os._exit(EXIT_HUNG)
