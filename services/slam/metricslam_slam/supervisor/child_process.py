"""One supervised child process of ``metricslam up`` (:class:`Child`) and the bounded tail of its
output kept for error messages when there is no ``--log-dir``.

Split out of :mod:`.launcher` (which re-exports :class:`Child` and :data:`TAIL_LINES`).
"""

from __future__ import annotations

import collections
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

from metricslam_slam.supervisor.liveness import Probe

# the launcher's logger, as before the split (its records keep their logger name)
log = logging.getLogger("metricslam_slam.supervisor.launcher")

#: output lines of a child kept for error messages (``metricslam up`` without ``--log-dir``)
TAIL_LINES = 20


def _drain(stream, tail: collections.deque) -> None:
    """Read a child's output to its end, keeping the last lines (decoded, never raising)."""
    try:
        for raw in stream:
            tail.append(raw.decode("utf-8", errors="replace").rstrip())
    except (OSError, ValueError):
        pass  # the pipe closed under us
    finally:
        stream.close()  # _wait_drained: the whole output is in


def _wait_drained(process: subprocess.Popen, timeout_s: float = 2.0) -> None:
    """Give the drain thread of an exited ``process`` a moment to read its last lines (it
    closes the pipe at the end of the output)."""
    deadline = time.monotonic() + timeout_s
    while not process.stdout.closed and time.monotonic() < deadline:
        time.sleep(0.01)


def _file_tail(path: str, lines: int) -> list[str]:
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - 64 * 1024))
            text = f.read().decode("utf-8", errors="replace")
    except OSError:
        return []
    return [line for line in text.splitlines() if line.strip()][-lines:]


@dataclass
class Child:
    """One supervised process."""

    name: str
    argv: list[str]
    ready: Callable[[], bool]
    where: str
    process: subprocess.Popen | None = None
    restarts: int = 0
    log_path: str | None = None
    #: ports it binds: ``(host, port, socket type, how to pick another port)``
    binds: list[tuple[str, int, int, str]] = field(default_factory=list)
    crashes_in_a_row: int = 0
    started_at_s: float = 0.0  # time.monotonic() of the latest start
    restart_at_s: float | None = None  # when a scheduled restart is due
    #: liveness probe (True: it answered), None: being alive is enough (:mod:`.liveness`)
    probe: Probe | None = None
    last_answer_s: float | None = None  # time.monotonic() of its latest answer to ``probe``
    hung_kills: int = 0
    _log_file: object = field(default=None, repr=False)
    #: the latest start's last output lines when there is no ``log_path`` (else the file has them)
    _tail: collections.deque = field(default_factory=lambda: collections.deque(maxlen=TAIL_LINES),
                                     repr=False)

    def start(self) -> None:
        self.started_at_s = time.monotonic()
        out = subprocess.PIPE
        if self.log_path:
            if self._log_file is None:
                self._log_file = open(self.log_path, "ab")
            out = self._log_file
        wrapped = [sys.executable, "-m", "metricslam_slam.supervisor.child", str(os.getpid()), "--", *self.argv]
        self.process = subprocess.Popen(wrapped, stdout=out, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL)
        if out is subprocess.PIPE:
            # drained on a thread (a full pipe would block the child), keeping a bounded tail
            self._tail = collections.deque(maxlen=TAIL_LINES)
            threading.Thread(target=_drain, args=(self.process.stdout, self._tail),
                             name=f"{self.name}-output", daemon=True).start()

    def output_tail(self, lines: int = TAIL_LINES) -> list[str]:
        """The last ``lines`` non-blank lines the latest process printed (stdout and stderr),
        from ``log_path`` when there is one. Call it after the process exited: a line still
        being read may be missing while it runs."""
        if self.process is not None and self.process.stdout is not None and self.process.poll() is not None:
            _wait_drained(self.process)
        if self.log_path:
            return _file_tail(self.log_path, lines)
        return [line for line in list(self._tail) if line.strip()][-lines:]

    def failure(self, when: str = "") -> str:
        """``<name> exited with code N<when>`` plus where to read why: the log file when there
        is one, and its last output lines, indented, one per line."""
        code = self.process.returncode if self.process is not None else None
        tail = self.output_tail()
        text = f"{self.name} exited with code {code}{when}"
        if self.log_path:
            text += f" (its output: {self.log_path})"
        if tail:
            text += "; its last output:\n" + "\n".join(f"  {self.name}| {line}" for line in tail)
        return text

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def kill(self) -> None:
        """SIGKILL and reap (a stopped process cannot act on SIGTERM)."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()

    def stop(self, grace_s: float) -> None:
        if self.process is None:
            return
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(grace_s)
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.0f s; killing it", self.name, grace_s)
                self.process.kill()
                self.process.wait()
        if self._log_file is not None:
            self._log_file.close()
            self._log_file = None
