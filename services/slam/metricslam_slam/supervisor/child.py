"""Exec a command that dies with its parent: ``python -m metricslam_slam.supervisor.child PPID -- CMD...``.

Sets ``PR_SET_PDEATHSIG`` (Linux; survives ``execve``) and replaces itself with ``CMD``, so a
child of ``metricslam up`` never outlives a launcher that was SIGKILLed. Done here rather than
in a ``preexec_fn`` because forking a multi-threaded launcher (zenoh runs threads) and running
Python between fork and exec can deadlock.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

_PR_SET_PDEATHSIG = 1


def main(argv: list[str]) -> int:
    if len(argv) < 3 or argv[1] != "--":
        print("usage: python -m metricslam_slam.supervisor.child PARENT_PID -- CMD [ARGS...]", file=sys.stderr)
        return 2
    parent_pid = int(argv[0])
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):  # not Linux: no parent-death signal, run anyway
        pass
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        return 1
    os.execv(argv[2], argv[2:])
    return 0  # not reached


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
