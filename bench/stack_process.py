"""The local stack as a fault benchmark drives it: ``metricslam up`` as a child process, the pids
of its children, a watcher of one camera, and a long sequence made from a short one.

* :class:`UpProcess` reads ``up``'s lines on a thread and keeps every ``NAME ready|restarted pid
  N`` and ``NAME hung`` line with its time (``time.perf_counter()``), so a benchmark knows each
  child's current pid (the pid ``up`` prints is the service itself: its ``child`` wrapper execs
  the command) and when the supervisor restarted what.
* :class:`Watcher` records a camera's poses (a :class:`PoseRecorder`, arrival times in
  ``perf_counter_ns``) and every ``…/status`` with its arrival time (depth link, events).
* :func:`ping_pong_sequence` writes a KITTI-layout folder (symlinked images) that plays a
  sequence forwards and backwards (:func:`~metricslam_slam.tools.soak.ping_pong`) with frame
  indices and 10 Hz timestamps that keep increasing, ground truth included, so a short sequence
  lasts as long as a fault needs.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from itertools import islice
from pathlib import Path

import numpy as np

CLI = [sys.executable, "-m", "metricslam_cli.main"]
#: what a child's command line contains, to check a pid before signalling it
CHILD_COMMANDS = {"zenoh-router": "metricslam_slam.supervisor.router", "depth-service": "depth-service",
                  "slam-service": "slam-service"}
_EVENT = re.compile(r"^(?P<name>[\w-]+)\s+(?P<what>ready|restarted|hung)\b(?:.*?\bpid (?P<pid>\d+))?")


def pick_port(base: int, taken: set[int], host: str = "127.0.0.1") -> int:
    """The first port from ``base`` on that is free now (bound and connected to:
    :func:`~metricslam_slam.supervisor.launcher.port_problem`) and not in ``taken``; adds it."""
    from metricslam_slam.supervisor.launcher import port_problem

    for port in range(base, base + 2000):
        if port not in taken and port_problem(host, port) is None:
            taken.add(port)
            return port
    raise RuntimeError(f"no free port in {base}..{base + 1999}")


def command_of(pid: int) -> str:
    """``/proc/<pid>/cmdline`` as one string ('' when the process is gone)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def running(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


class UpProcess:
    """``metricslam up ARGS`` with ``env``; :meth:`wait_up` blocks until its ``UP:`` line.

    Attributes:
        events: ``(t_s, child name, "ready"|"restarted"|"hung", pid or None)`` in order,
            ``t_s`` from ``time.perf_counter()``.
        lines: every line it printed.
    """

    def __init__(self, args: list[str], env: dict) -> None:
        self.proc = subprocess.Popen(CLI + ["up", *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, env=env)
        self.events: list[tuple[float, str, str, int | None]] = []
        self.lines: list[str] = []
        self._cond = threading.Condition()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        for line in self.proc.stdout:
            t_s = time.perf_counter()
            m = _EVENT.match(line)
            with self._cond:
                self.lines.append(line.rstrip())
                if m:
                    self.events.append((t_s, m["name"], m["what"], int(m["pid"]) if m["pid"] else None))
                self._cond.notify_all()

    def wait_up(self, timeout_s: float = 180.0) -> None:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not any(line.startswith("UP:") for line in self.lines):
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("metricslam up did not come up:\n" + "\n".join(self.lines[-20:]))
                self._cond.wait(0.5)

    def pid(self, name: str) -> int:
        """The latest pid ``up`` printed for child ``name``, checked against its command line."""
        with self._cond:
            pids = [pid for _, n, _, pid in self.events if n == name and pid is not None]
        if not pids or CHILD_COMMANDS[name] not in command_of(pids[-1]):
            raise RuntimeError(f"no running {name} among up's children (pids {pids})")
        return pids[-1]

    def events_after(self, t_s: float, what: str | None = None) -> list[tuple[float, str, str, int | None]]:
        with self._cond:
            return [e for e in self.events if e[0] >= t_s and (what is None or e[2] == what)]

    def stop(self, timeout_s: float = 60.0) -> int:
        """SIGINT (as Ctrl-C) and wait; SIGKILL if it hangs. Returns its exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


class Watcher:
    """One camera's poses (``recorder``) and ``…/status`` messages with arrival times.

    Attributes:
        statuses: ``(t_s, StatusMessage)``, ``t_s`` from ``time.perf_counter()``.
    """

    def __init__(self, session, camera_id: str) -> None:
        from metricslam.wire import keys
        from metricslam_slam.tools.client import PoseRecorder

        self.recorder = PoseRecorder(session, camera_id)
        self.statuses: list = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(keys.key(camera_id, "status"), self._on_status)

    def _on_status(self, sample) -> None:
        from metricslam.errors import CodecError
        from metricslam.wire.codec import StatusMessage, decode_as

        t_s = time.perf_counter()
        try:
            msg = decode_as(sample.payload.to_bytes(), StatusMessage)
        except CodecError:
            return
        with self._lock:
            self.statuses.append((t_s, msg))

    def arrivals_s(self) -> np.ndarray:
        """Sorted pose arrival times (s, ``perf_counter``)."""
        with self.recorder._cond:
            return np.sort(np.array(list(self.recorder.arrival_ns.values()), dtype=np.float64) / 1e9)

    def events(self) -> list[tuple[float, str, str]]:
        with self._lock:
            return [(t, s.event, s.event_detail or "") for t, s in self.statuses if s.event]

    def close(self) -> None:
        self._sub.undeclare()
        self.recorder.close()


def ping_pong_sequence(src: Path, out: Path, n_frames: int) -> np.ndarray | None:
    """Write ``out`` (KITTI layout): frame ``k`` is ``src``'s frame ``ping_pong(n)[k]``, at
    ``k × 0.1 s``, with ``src``'s ``calib.txt``; images are symlinks. Returns the matching
    ground truth ``T_world_cam`` (n_frames, 4, 4), also written to ``out/poses/pingpong.txt``,
    or None when ``src`` has none."""
    from metricslam.datasets import open_sequence
    from metricslam.trajectory.io import write_kitti_poses
    from metricslam_slam.tools.soak import ping_pong

    seq = open_sequence(src)
    images = sorted((src / "image_0").glob("*.png"))
    if len(images) != len(seq) or len(images) < 2:
        raise RuntimeError(f"{src}: expected a KITTI folder with image_0/*.png, got {len(images)} images")
    order = list(islice(ping_pong(len(images)), n_frames))
    (out / "image_0").mkdir(parents=True)
    for k, i in enumerate(order):
        os.symlink(images[i].resolve(), out / "image_0" / f"{k:06d}.png")
    shutil.copy(src / "calib.txt", out / "calib.txt")
    (out / "times.txt").write_text("".join(f"{k / 10:.6e}\n" for k in range(n_frames)))
    gt = getattr(seq, "T_world_cam_gt", None)
    if gt is None:
        return None
    gt = np.asarray(gt)[order]
    (out / "poses").mkdir()
    write_kitti_poses(out / "poses" / "pingpong.txt", gt)
    return gt
