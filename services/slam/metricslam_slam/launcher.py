"""``metricslam up``: the local stack as supervised child processes.

Starts, in order, a Zenoh router (``python -m metricslam_slam.router``), the depth service
(``metricslam depth-service``) and the SLAM service (``metricslam slam-service``), waits until each
is ready (router: TCP port open; depth: ``/readyz`` 200; SLAM: answers
``metricslam/_service/health``), prints where everything listens, then supervises: a child that
dies is restarted after ``restart_delay_s`` (like compose's ``restart: unless-stopped``), so
killing the depth service degrades the stack (no new scale factors) instead of ending it.
SIGINT/SIGTERM stop the children in reverse order (SIGTERM, then SIGKILL after a grace period).
Children are started through ``metricslam_slam.child`` (``PR_SET_PDEATHSIG``) so they never
outlive a killed launcher.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import httpx

from metricslam.endpoints import DEFAULT_DEPTH_HOST, DEFAULT_DEPTH_PORT, depth_url
from metricslam.errors import ServiceError
from metricslam_slam.zenoh_config import check_endpoint

log = logging.getLogger(__name__)


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
    _log_file: object = field(default=None, repr=False)

    def start(self) -> None:
        out = subprocess.DEVNULL
        if self.log_path:
            self._log_file = open(self.log_path, "ab")
            out = self._log_file
        wrapped = [sys.executable, "-m", "metricslam_slam.child", str(os.getpid()), "--", *self.argv]
        self.process = subprocess.Popen(wrapped, stdout=out, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL)

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

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


def _port_open(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


def _http_ready(url: str) -> bool:
    try:
        return httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200
    except httpx.HTTPError:
        return False


def slam_ready(endpoint: str) -> bool:
    from metricslam_slam.client import query_health
    from metricslam_slam.zenoh_config import open_client

    try:
        session = open_client(endpoint)
    except ServiceError:
        return False
    try:
        health = query_health(session, timeout_s=1.0)
        return bool(health and health.get("ready"))
    finally:
        session.close()


class Stack:
    """The router, depth and SLAM services as children of this process.

    Args:
        zenoh_endpoint: router listen endpoint, ``tcp/HOST:PORT``.
        depth_port / depth_host: where the depth service listens; ``depth_port=None`` runs
            without a depth service (the SLAM service then uses the in-process model, or no
            scale with ``use_scale=False``).
        use_scale, preset, session_kind: passed to the SLAM service.
        config_path: the SLAM service's system config file (``--config``; else its children
            inherit ``METRICSLAM_CONFIG`` from this process's environment).
        log_dir: children's stdout/stderr go to ``<log_dir>/<name>.log`` (else discarded).
        rerun: live view target of the SLAM service (``web`` or ``FILE.rrd``).
    """

    def __init__(self, zenoh_endpoint: str, depth_port: int | None = DEFAULT_DEPTH_PORT,
                 depth_host: str = DEFAULT_DEPTH_HOST,
                 use_scale: bool = True, preset: str | None = None, session_kind: str = "pipeline",
                 log_dir: str | None = None, restart_delay_s: float = 1.0,
                 ready_timeout_s: float = 60.0, rerun: str | None = None,
                 config_path: str | None = None) -> None:
        check_endpoint(zenoh_endpoint)
        logging.getLogger("httpx").setLevel(logging.WARNING)
        self.zenoh_endpoint = zenoh_endpoint
        self.restart_delay_s = restart_delay_s
        self.ready_timeout_s = ready_timeout_s
        self._stop = threading.Event()
        _, _, hostport = zenoh_endpoint.partition("/")
        zhost, _, zport = hostport.rpartition(":")
        zhost = "127.0.0.1" if zhost in ("0.0.0.0", "[::]") else zhost
        py = [sys.executable, "-m"]
        cli = py + ["metricslam.cli.main"]
        self.depth_url = None if depth_port is None else depth_url(depth_host, depth_port)
        self.children = [Child("zenoh-router", py + ["metricslam_slam.router", "--listen", zenoh_endpoint],
                               lambda: _port_open(zhost, int(zport)), zenoh_endpoint)]
        if self.depth_url is not None and use_scale:
            self.children.append(Child(
                "depth-service", cli + ["depth-service", "--host", depth_host, "--port", str(depth_port)],
                lambda: _http_ready(self.depth_url), self.depth_url))
        slam = cli + ["slam-service", "--zenoh-endpoint", zenoh_endpoint, "--session", session_kind,
                      "--depth-url", self.depth_url if (self.depth_url and use_scale) else "none"]
        if not use_scale:
            slam.append("--no-scale")
        if preset:
            slam += ["--preset", preset]
        if rerun:
            slam += ["--rerun", rerun]
        if config_path:
            slam += ["--config", str(config_path)]
        self.children.append(Child("slam-service", slam, lambda: slam_ready(zenoh_endpoint),
                                   f"{zenoh_endpoint} (metricslam/<camera_id>/{{frame,pose,keyframe,status,trajectory}})"))
        if log_dir:
            for child in self.children:
                child.log_path = f"{log_dir}/{child.name}.log"

    def _wait_ready(self, child: Child) -> None:
        deadline = time.monotonic() + self.ready_timeout_s
        while not child.ready():
            if not child.alive():
                raise ServiceError(f"{child.name} exited with code {child.process.returncode} while "
                                   f"starting{'; see ' + child.log_path if child.log_path else ''}")
            if time.monotonic() > deadline or self._stop.is_set():
                raise ServiceError(f"{child.name} not ready after {self.ready_timeout_s:.0f} s")
            time.sleep(0.2)

    def start(self, on_ready: Callable[[Child], None] = lambda c: None) -> None:
        """Start every child in order and wait for each to be ready; stops all on failure."""
        try:
            for child in self.children:
                child.start()
                self._wait_ready(child)
                on_ready(child)
        except BaseException:
            self.stop()
            raise

    def supervise(self, on_restart: Callable[[Child], None] = lambda c: None, poll_s: float = 0.5) -> None:
        """Restart dead children until :meth:`request_stop`."""
        while not self._stop.wait(poll_s):
            for child in self.children:
                if not child.alive() and not self._stop.is_set():
                    log.warning("%s exited (code %s); restarting in %.1f s", child.name,
                                child.process.returncode, self.restart_delay_s)
                    if self._stop.wait(self.restart_delay_s):
                        return
                    child.restarts += 1
                    child.start()
                    on_restart(child)

    def request_stop(self) -> None:
        self._stop.set()

    def stop(self, grace_s: float = 10.0) -> None:
        """Stop the children in reverse start order."""
        self._stop.set()
        for child in reversed(self.children):
            child.stop(grace_s)
