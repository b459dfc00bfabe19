"""Issue #19 item 4: ``metricslam up`` sees a child that is alive but no longer answers.

A stopped (SIGSTOP) depth service keeps its pid and its listening socket, so ``poll()`` and a
port check both call it healthy; the liveness probe (``GET /healthz``) does not answer, and the
launcher kills and restarts it within the configured ``--hang-timeout``. The unit tests pin the
rules without processes of the stack: a silent child is killed after the timeout and restarted
with the usual backoff; a child reached through a silent router is not blamed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

from metricslam_slam.supervisor.launcher import Child, Stack, free_port
from metricslam_slam.supervisor.liveness import LivenessMonitor

from child_process import LineReader, interrupt_and_wait

CLI = [sys.executable, "-m", "metricslam_cli.main"]
SLEEPER = [sys.executable, "-c", "import time; time.sleep(600)"]


def _stack(hang_timeout_s: float) -> Stack:
    return Stack(f"tcp/127.0.0.1:{free_port()}", depth_port=None, restart_delay_s=0.1,
                 restart_delay_max_s=0.4, hang_timeout_s=hang_timeout_s, probe_period_s=0.1,
                 ready_timeout_s=0.5)


def test_a_silent_child_is_killed_and_restarted_after_the_hang_timeout() -> None:
    stack = _stack(hang_timeout_s=1.0)
    answers = {"ok": True}
    child = Child("sleeper", SLEEPER, lambda: True, "nowhere", probe=lambda: answers["ok"])
    stack.children = [child]
    child.start()
    child.last_answer_s = time.monotonic()
    first_pid = child.process.pid
    hung: list[float] = []
    restarted = threading.Event()
    worker = threading.Thread(target=stack.supervise, daemon=True, kwargs={
        "poll_s": 0.05, "on_hung": lambda c, s: hung.append(s), "on_restart": lambda c: restarted.set()})
    worker.start()
    try:
        time.sleep(1.5)  # answering: left alone beyond the timeout
        assert not hung and child.process.pid == first_pid
        answers["ok"] = False
        t_silent = time.monotonic()
        assert restarted.wait(10), "the silent child was not restarted"
        elapsed_s = time.monotonic() - t_silent
        assert hung and 1.0 < hung[0] < 2.5 and elapsed_s < 3.0, (hung, elapsed_s)
        assert child.process.pid != first_pid and child.hung_kills == 1 and child.restarts == 1
        answers["ok"] = True  # the new one answers: it stays
        time.sleep(1.5)
        assert child.hung_kills == 1
    finally:
        stack.request_stop()
        worker.join(10)
        stack.stop(grace_s=1.0)


def test_hang_timeout_zero_probes_nothing() -> None:
    stack = _stack(hang_timeout_s=0.0)
    child = Child("sleeper", SLEEPER, lambda: True, "nowhere", probe=lambda: False)
    child.start()
    try:
        assert stack.hung_for_s(child, time.monotonic() + 1e6) is None
    finally:
        child.kill()


def test_a_child_behind_a_silent_router_is_not_blamed() -> None:
    class Fake:
        def __init__(self, name: str, answers: bool, alive: bool = True) -> None:
            self.name, self.answers, self._alive = name, answers, alive
            self.probe = lambda: self.answers
            self.last_answer_s = None

        def alive(self) -> bool:
            return self._alive

    router, slam = Fake("zenoh-router", False), Fake("slam-service", False)
    monitor = LivenessMonitor([router, slam], 1.0, gate={"slam-service": "zenoh-router"})
    assert monitor.probe_once() == {"zenoh-router": False, "slam-service": True}
    assert router.last_answer_s is None and slam.last_answer_s is not None
    router.answers = True
    assert monitor.probe_once() == {"zenoh-router": True, "slam-service": False}
    router._alive = False  # being restarted
    assert monitor.probe_once()["slam-service"] is True


def test_bad_liveness_settings_are_refused() -> None:
    from metricslam.errors import ServiceError

    with pytest.raises(ServiceError, match="probe-period"):
        Stack(f"tcp/127.0.0.1:{free_port()}", depth_port=None, probe_period_s=0)


def _gone(pid: int) -> bool:
    stat = Path(f"/proc/{pid}/stat")
    return not stat.exists() or stat.read_text().split()[2] == "Z"


@pytest.mark.slow
def test_up_restarts_a_stopped_depth_service_within_the_hang_timeout(tmp_path: Path) -> None:
    hang_timeout_s, probe_period_s = 3.0, 0.5
    depth_port = free_port()
    up = subprocess.Popen(CLI + ["up", "--zenoh-endpoint", f"tcp/127.0.0.1:{free_port()}",
                                 "--depth-port", str(depth_port), "--session", "identity",
                                 "--hang-timeout", str(hang_timeout_s),
                                 "--probe-period", str(probe_period_s), "--restart-delay", "0.5",
                                 "--log-dir", str(tmp_path / "logs")],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
    lines = LineReader(up)
    stopped_pid = None
    try:
        stopped_pid = int(lines.wait("depth-service", 90).split("pid")[1].split()[0])
        lines.wait("UP:", 90)
        os.kill(stopped_pid, signal.SIGSTOP)
        t_stop = time.monotonic()
        hung = lines.wait("depth-service  hung", hang_timeout_s + 30)
        detected_s = time.monotonic() - t_stop
        restarted = lines.wait("depth-service  restarted", 30)
        # silent for the limit (counted from its last answer, which may precede the stop) and
        # noticed within a probe period and a probe's own timeout; generous for a loaded machine
        silent_s = float(hung.split("for")[1].split()[0])
        assert silent_s >= hang_timeout_s, hung
        assert detected_s <= hang_timeout_s + 2 * probe_period_s + 5.0, (detected_s, hung)
        new_pid = int(restarted.split("pid")[1].split()[0])
        assert new_pid != stopped_pid
        deadline = time.monotonic() + 60
        while not _gone(stopped_pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _gone(stopped_pid), "the hung depth service was not killed"
        ok = False
        while not ok and time.monotonic() < deadline:  # the new one serves on the same port
            try:
                ok = httpx.get(f"http://127.0.0.1:{depth_port}/healthz", timeout=1.0).status_code == 200
            except httpx.HTTPError:
                time.sleep(0.3)
        assert ok, "the restarted depth service does not answer"
    finally:
        if stopped_pid is not None and not _gone(stopped_pid):
            os.kill(stopped_pid, signal.SIGKILL)
        interrupt_and_wait(up)
    assert up.returncode == 0
