"""``metricslam up``: the local stack as supervised child processes.

Starts, in order, a Zenoh router (``python -m metricslam_slam.supervisor.router``), the depth service
(``metricslam depth-service``) and the SLAM service (``metricslam slam-service``), waits until each
is ready (router: TCP port open; depth: ``/readyz`` 200; SLAM: answers
``metricslam/_service/health``), prints where everything listens, then supervises: a child that
dies is restarted (like compose's ``restart: unless-stopped``), so killing the depth service
degrades the stack (no new scale factors) instead of ending it. A child that is alive but no
longer answers its health probe (:mod:`.liveness`: router query, depth ``/healthz``, SLAM health
query) for ``hang_timeout_s`` is killed and restarted the same way. A child that keeps crashing is
restarted with exponential backoff (``restart_delay_s``, doubling up to ``restart_delay_max_s``;
a child that ran ``stable_after_s`` starts again from ``restart_delay_s``).

Before starting anything, every port the stack will bind (router, depth service) is checked:
the readiness probes cannot tell our child from another process on the same port, so a taken
port would read as "ready" and the real child would crash and restart forever. A taken port is
refused with :class:`~metricslam.errors.ServiceError` naming it and the flag that moves it.
SIGINT/SIGTERM stop the children in reverse order (SIGTERM, then SIGKILL after a grace period).
Children are started through ``metricslam_slam.supervisor.child`` (``PR_SET_PDEATHSIG``) so they never
outlive a killed launcher.
"""

from __future__ import annotations

import errno
import logging
import socket
import sys
import threading
import time
from typing import Callable

import httpx

from metricslam.endpoints import DEFAULT_DEPTH_HOST, DEFAULT_DEPTH_PORT, depth_url
from metricslam.errors import ServiceError
from metricslam_slam.supervisor.child_process import TAIL_LINES as TAIL_LINES  # re-exported
from metricslam_slam.supervisor.child_process import Child
from metricslam_slam.supervisor.liveness import LivenessMonitor, ZenohProbe, http_healthz
from metricslam_slam.zenoh_config import check_endpoint

log = logging.getLogger(__name__)


def _port_open(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


def restart_delay_s(crashes_in_a_row: int, first_s: float, max_s: float) -> float:
    """Backoff before restart number ``crashes_in_a_row`` (1, 2, …): ``first_s·2^(n−1)``,
    at most ``max_s`` (1, 2, 4, 8, 16, 30, 30 … s with the defaults)."""
    return min(max_s, first_s * 2.0 ** max(crashes_in_a_row - 1, 0))


def port_problem(host: str, port: int, sock_type: int = socket.SOCK_STREAM) -> str | None:
    """Why ``host:port`` cannot be bound now (``"is in use"``, or the OS error), or None if free.

    Checks by binding (with ``SO_REUSEADDR``, as uvicorn and the router do, so ports in
    TIME_WAIT count as free) and, for TCP, by connecting: something that accepts connections
    there would answer our readiness probes.
    """
    bind_host = host.strip("[]")
    probe_host = {"0.0.0.0": "127.0.0.1", "": "127.0.0.1", "::": "::1"}.get(bind_host, bind_host)
    if sock_type == socket.SOCK_STREAM and _port_open(probe_host, port):
        return "is in use"
    family = socket.AF_INET6 if ":" in bind_host else socket.AF_INET
    with socket.socket(family, sock_type) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((bind_host, port))
        except OSError as exc:
            return "is in use" if exc.errno == errno.EADDRINUSE else f"cannot be bound ({exc.strerror})"
    return None


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free now (for suggestions in error messages and for tests)."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as sock:
        sock.bind((host.strip("[]"), 0))
        return int(sock.getsockname()[1])


def _http_ready(url: str) -> bool:
    try:
        return httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200
    except httpx.HTTPError:
        return False


def slam_ready(endpoint: str) -> bool:
    from metricslam_slam.tools.client import query_health
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
        state_dir: the SLAM service's state directory (``--state-dir``: each camera's
            trajectory, so a restarted SLAM child continues its cameras as new linked segments);
            None: its ``SLAM_STATE_DIR``, if any, from this process's environment.
        log_dir: children's stdout/stderr go to ``<log_dir>/<name>.log``; else only the last
            :data:`TAIL_LINES` lines of each are kept, and printed when it fails.
        rerun: live view target of the SLAM service (``web`` or ``FILE.rrd``).
        hang_timeout_s: a child whose health probe has not answered for this long is killed and
            restarted (0: no liveness probes, only exits are noticed). A restarted child has
            ``max(hang_timeout_s, ready_timeout_s)`` to answer for the first time.
        probe_period_s: time between probe rounds (each probe waits at most this, capped at 2 s).
        scale_sources / mount_height_m: the SLAM service's ``--scale-sources`` (comma-separated)
            and ``--mount-height`` (m); None: its config's (docs/ground_scale.md).
        depth_model: the depth service's ``--model`` (ONNX path); None: its ``DEPTH_MODEL_PATH``
            or the shipped default.
    """

    def __init__(self, zenoh_endpoint: str, depth_port: int | None = DEFAULT_DEPTH_PORT,
                 depth_host: str = DEFAULT_DEPTH_HOST,
                 use_scale: bool = True, preset: str | None = None, session_kind: str = "pipeline",
                 log_dir: str | None = None, restart_delay_s: float = 1.0,
                 ready_timeout_s: float = 60.0, rerun: str | None = None,
                 config_path: str | None = None, restart_delay_max_s: float = 30.0,
                 stable_after_s: float = 30.0, hang_timeout_s: float = 20.0,
                 probe_period_s: float = 2.0, state_dir: str | None = None,
                 scale_sources: str | None = None, mount_height_m: float | None = None,
                 depth_model: str | None = None) -> None:
        check_endpoint(zenoh_endpoint)
        if hang_timeout_s < 0 or probe_period_s <= 0:
            raise ServiceError(f"--hang-timeout must be >= 0 and --probe-period > 0 s, got "
                               f"{hang_timeout_s:g} and {probe_period_s:g}")
        logging.getLogger("httpx").setLevel(logging.WARNING)
        self.zenoh_endpoint = zenoh_endpoint
        self.restart_delay_s = restart_delay_s
        self.restart_delay_max_s = max(restart_delay_max_s, restart_delay_s)
        self.stable_after_s = stable_after_s
        self.ready_timeout_s = ready_timeout_s
        self.hang_timeout_s = hang_timeout_s
        self.probe_period_s = probe_period_s
        probe_timeout_s = min(probe_period_s, 2.0)
        self._zenoh_probe = ZenohProbe(zenoh_endpoint, probe_timeout_s)
        self._stop = threading.Event()
        self._stop_requested = False  # request_stop(): a plain flag, safe in a signal handler
        zproto, _, hostport = zenoh_endpoint.partition("/")
        zbind, _, zport = hostport.rpartition(":")
        zhost = "127.0.0.1" if zbind in ("0.0.0.0", "[::]") else zbind
        py = [sys.executable, "-m"]
        # the children are the `metricslam` commands an operator would run: a process boundary,
        # not an import (the services floor never imports the CLI; pyproject import contracts)
        cli = py + ["metricslam_cli.main"]
        self.depth_url = None if depth_port is None else depth_url(depth_host, depth_port)
        zsock = socket.SOCK_DGRAM if zproto in ("udp", "quic") else socket.SOCK_STREAM
        self.children = [Child("zenoh-router", py + ["metricslam_slam.supervisor.router", "--listen", zenoh_endpoint],
                               lambda: _port_open(zhost, int(zport)), zenoh_endpoint,
                               binds=[(zbind, int(zport), zsock,
                                       f"--zenoh-endpoint {zproto}/{zbind}:<PORT>")],
                               probe=self._zenoh_probe.router)]
        if self.depth_url is not None and use_scale:
            self.children.append(Child(
                "depth-service", cli + ["depth-service", "--host", depth_host, "--port", str(depth_port)]
                + (["--model", str(depth_model)] if depth_model else []),
                lambda: _http_ready(self.depth_url), self.depth_url,
                binds=[(depth_host, int(depth_port), socket.SOCK_STREAM, "--depth-port <PORT>")],
                probe=lambda: http_healthz(self.depth_url, probe_timeout_s)))
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
        if state_dir:
            slam += ["--state-dir", str(state_dir)]
        if scale_sources:
            slam += ["--scale-sources", str(scale_sources)]
        if mount_height_m is not None:
            slam += ["--mount-height", repr(float(mount_height_m))]
        self.children.append(Child("slam-service", slam, lambda: slam_ready(zenoh_endpoint),
                                   f"{zenoh_endpoint} (metricslam/<camera_id>/{{frame,pose,keyframe,status,trajectory}})"
                                   + (f"; state in {state_dir}" if state_dir else ""),
                                   probe=self._zenoh_probe.slam))
        if log_dir:
            for child in self.children:
                child.log_path = f"{log_dir}/{child.name}.log"

    def check_ports(self) -> None:
        """Refuse to start when a port the stack will bind is taken (or cannot be bound).

        Raises:
            ServiceError: naming each such port, its service, and the flag that moves it.
        """
        problems = []
        claimed: dict[tuple[int, int], str] = {}
        for child in self.children:
            for host, port, sock_type, flag in child.binds:
                why = port_problem(host, port, sock_type)
                if why is None and (port, sock_type) in claimed:
                    why = f"is also the {claimed[(port, sock_type)]}'s port"
                claimed[(port, sock_type)] = child.name
                if why is not None:
                    held = ", or stop the process holding it (`ss -ltnp` shows it)" if why == "is in use" else ""
                    problems.append(f"port {port} for the {child.name} ({host}:{port}) {why}: "
                                    f"choose another with {flag.replace('<PORT>', str(free_port()))} "
                                    f"(free right now){held}")
        if problems:
            raise ServiceError("cannot start the stack: " + "; ".join(problems))

    def _wait_ready(self, child: Child) -> None:
        deadline = time.monotonic() + self.ready_timeout_s
        while True:
            # alive first: a child that died must not pass for ready because something else answers
            if not child.alive():
                raise ServiceError(child.failure(" while starting"))
            if child.ready():
                return
            if time.monotonic() > deadline or self._stopping():
                raise ServiceError(f"{child.name} not ready after {self.ready_timeout_s:.0f} s")
            time.sleep(0.2)

    def start(self, on_ready: Callable[[Child], None] = lambda c: None) -> None:
        """Check the ports, then start every child in order and wait for each to be ready;
        stops all on failure."""
        self.check_ports()
        try:
            for child in self.children:
                child.start()
                self._wait_ready(child)
                child.last_answer_s = time.monotonic()  # ready is an answer
                on_ready(child)
        except BaseException:
            self.stop()
            raise

    def supervise(self, on_restart: Callable[[Child], None] = lambda c: None, poll_s: float = 0.5,
                  on_hung: Callable[[Child, float], None] = lambda c, s: None) -> None:
        """Restart dead children until :meth:`request_stop`, with exponential backoff for a
        child that keeps crashing (one child's backoff never delays another's restart); kill a
        child silent for ``hang_timeout_s`` first (``on_hung(child, silent_s)``), so it is
        restarted the same way."""
        monitor = None
        if self.hang_timeout_s > 0:
            monitor = LivenessMonitor(self.children, self.probe_period_s,
                                      gate={"slam-service": "zenoh-router"}).start()
        try:
            self._supervise(on_restart, poll_s, on_hung)
        finally:
            if monitor is not None:
                monitor.stop()

    def _supervise(self, on_restart, poll_s: float, on_hung) -> None:
        while not self._stop.wait(poll_s) and not self._stop_requested:
            for child in self.children:
                if self._stopping():
                    return
                now = time.monotonic()
                silent_s = self.hung_for_s(child, now)
                if silent_s is not None:
                    log.warning("%s (pid %d) has not answered its health probe for %.1f s (limit "
                                "%.3g s): hung; killing it", child.name, child.process.pid, silent_s,
                                self.hang_timeout_s)
                    child.kill()
                    child.hung_kills += 1
                    on_hung(child, silent_s)
                if child.alive():
                    continue
                if child.restart_at_s is None:
                    self._schedule_restart(child, now)
                elif now >= child.restart_at_s:
                    child.restart_at_s = None
                    child.restarts += 1
                    child.start()
                    on_restart(child)

    def hung_for_s(self, child: Child, now_s: float) -> float | None:
        """Seconds ``child`` (alive, with a probe) has been silent past its limit, else None:
        ``hang_timeout_s`` since its last answer, or since its start with
        ``max(hang_timeout_s, ready_timeout_s)`` when it has not answered since."""
        if self.hang_timeout_s <= 0 or child.probe is None or not child.alive():
            return None
        answered = child.last_answer_s is not None and child.last_answer_s >= child.started_at_s
        silent_s = now_s - (child.last_answer_s if answered else child.started_at_s)
        limit_s = self.hang_timeout_s if answered else max(self.hang_timeout_s, self.ready_timeout_s)
        return silent_s if silent_s > limit_s else None

    def _schedule_restart(self, child: Child, now: float) -> None:
        ran_s = now - child.started_at_s
        child.crashes_in_a_row = 1 if ran_s >= self.stable_after_s else child.crashes_in_a_row + 1
        delay_s = restart_delay_s(child.crashes_in_a_row, self.restart_delay_s, self.restart_delay_max_s)
        child.restart_at_s = now + delay_s
        tail = child.output_tail(5)
        log.warning("%s exited with code %s after %.1f s (%d time(s) in a row); restarting in %.3g s "
                    "(backoff doubles up to %.3g s)%s%s", child.name, child.process.returncode, ran_s,
                    child.crashes_in_a_row, delay_s, self.restart_delay_max_s,
                    f"; its output: {child.log_path}" if child.log_path else "",
                    "; its last output:\n" + "\n".join(f"  {child.name}| {line}" for line in tail)
                    if tail else "")

    def request_stop(self) -> None:
        """Ask :meth:`supervise` to return (within its poll period). Safe in a signal handler: it
        takes no lock (setting the Event there could deadlock on the one ``wait`` holds)."""
        self._stop_requested = True

    def _stopping(self) -> bool:
        return self._stop_requested or self._stop.is_set()

    def stop(self, grace_s: float = 10.0) -> None:
        """Stop the children in reverse start order."""
        self._stop.set()
        for child in reversed(self.children):
            child.stop(grace_s)
        self._zenoh_probe.close()
