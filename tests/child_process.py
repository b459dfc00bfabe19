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
