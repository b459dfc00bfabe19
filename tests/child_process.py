"""Test support: stopping a child process the way a user would (Ctrl-C), then for sure."""

from __future__ import annotations

import signal
import subprocess


def interrupt_and_wait(proc: subprocess.Popen, timeout_s: float = 30.0) -> None:
    """SIGINT the child and wait up to ``timeout_s`` seconds for it; SIGKILL it if it hangs."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


class LineReader:
    """Reads a child's stdout lines on a thread so a test can wait for one with a timeout."""

    def __init__(self, proc: subprocess.Popen) -> None:
        import queue
        import threading

        self._empty = queue.Empty
        self.q: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=lambda: [self.q.put(line) for line in proc.stdout], daemon=True).start()

    def wait(self, prefix: str, timeout_s: float) -> str:
        """The first new line starting with ``prefix``; AssertionError after ``timeout_s``."""
        import time

        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self.q.get(timeout=0.5)
            except self._empty:
                continue
            self.seen.append(line)
            if line.startswith(prefix):
                return line
        raise AssertionError(f"no line starting with {prefix!r} in {timeout_s} s; got {self.seen}")
