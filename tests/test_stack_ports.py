"""Issue #19: ``metricslam up`` on a taken port refuses at once instead of reporting "ready"
(its probe reached the other process) and restarting its own child forever; a child that keeps
crashing is restarted with exponential backoff."""

from __future__ import annotations

import logging
import re
import socket
import subprocess
import sys
import threading
import time

import pytest
from metricslam.errors import ServiceError
from metricslam_slam.supervisor.launcher import Child, Stack, free_port, port_problem, restart_delay_s

CLI = [sys.executable, "-m", "metricslam_cli.main"]


@pytest.fixture()
def taken_port():
    """A plain TCP listener on 127.0.0.1 (some other program): yields its port."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        yield sock.getsockname()[1]


def _listening(port: int) -> bool:
    with socket.socket() as sock:
        sock.settimeout(0.5)
        return sock.connect_ex(("127.0.0.1", port)) == 0


def test_up_refuses_a_taken_depth_port_before_starting_anything(taken_port):
    router_port = free_port()
    t0 = time.monotonic()
    out = subprocess.run(CLI + ["up", "--zenoh-endpoint", f"tcp/127.0.0.1:{router_port}",
                                "--depth-port", str(taken_port)],
                         capture_output=True, text=True, timeout=60)
    elapsed_s = time.monotonic() - t0
    assert out.returncode != 0, out.stdout
    assert elapsed_s < 15, f"took {elapsed_s:.1f} s to refuse"
    assert f"port {taken_port}" in out.stderr and "--depth-port" in out.stderr, out.stderr
    assert "ready" not in out.stdout and "UP" not in out.stdout
    assert not _listening(router_port)  # the router was never started


def test_taken_router_port_and_shared_ports_are_refused(taken_port):
    stack = Stack(f"tcp/127.0.0.1:{taken_port}", depth_port=free_port())
    with pytest.raises(ServiceError, match=rf"port {taken_port} .*zenoh-router.*--zenoh-endpoint tcp/127\.0\.0\.1:\d+"):
        stack.check_ports()
    port = free_port()
    with pytest.raises(ServiceError, match=rf"port {port} .*also the zenoh-router's port.*--depth-port"):
        Stack(f"tcp/127.0.0.1:{port}", depth_port=port).check_ports()
    assert port_problem("127.0.0.1", taken_port) == "is in use"
    assert port_problem("0.0.0.0", taken_port) == "is in use"  # binding every interface clashes too
    assert port_problem("127.0.0.1", free_port()) is None


def test_restart_delay_doubles_up_to_its_cap():
    assert [restart_delay_s(n, 1.0, 30.0) for n in range(1, 8)] == [1, 2, 4, 8, 16, 30, 30]


def test_a_crashing_child_is_restarted_with_backoff(caplog):
    stack = Stack(f"tcp/127.0.0.1:{free_port()}", depth_port=None, restart_delay_s=0.1,
                  restart_delay_max_s=0.4, stable_after_s=60.0)
    crasher = Child("crasher", [sys.executable, "-c", "raise SystemExit(3)"], lambda: True, "nowhere")
    stack.children = [crasher]
    restarts: list[float] = []
    crasher.start()
    with caplog.at_level(logging.WARNING, logger="metricslam_slam.supervisor.launcher"):
        worker = threading.Thread(target=stack.supervise,
                                  kwargs={"on_restart": lambda c: restarts.append(time.monotonic()),
                                          "poll_s": 0.02})
        worker.start()
        try:
            deadline = time.monotonic() + 30
            while len(restarts) < 4 and time.monotonic() < deadline:
                time.sleep(0.05)
        finally:
            stack.request_stop()
            worker.join(10)
            crasher.stop(5)
    assert len(restarts) >= 4
    lines = [r.getMessage() for r in caplog.records if "restarting in" in r.getMessage()]
    delays = [float(re.search(r"restarting in ([\d.]+) s", text).group(1)) for text in lines]
    assert delays[:4] == [0.1, 0.2, 0.4, 0.4]
    assert "crasher exited with code 3" in lines[0] and "(3 time(s) in a row)" in lines[2]
    gaps = [b - a for a, b in zip(restarts, restarts[1:])]
    assert gaps[1] >= 0.4 and gaps[2] >= 0.4  # restart n+1 waits for delay n+1 at least
