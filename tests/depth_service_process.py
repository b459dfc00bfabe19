"""Test support: start the real depth service as a child process (``metricslam depth-service``)
and wait for it.

Used by the tests and the benchmarks (``from tests.depth_service_process import ServiceProcess``,
from the repository root), so both talk HTTP to exactly what an operator runs::

    with ServiceProcess(port=18101, settings={"max_queue": 2}) as service:
        httpx.get(service.url + "/readyz")
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from types import TracebackType

import httpx

from metricslam.errors import ServiceError


class ServiceProcess:
    """A depth service in a child process on ``127.0.0.1:port``.

    Args:
        port: TCP port on loopback.
        settings: extra ``DepthServiceSettings`` fields, passed as ``DEPTH_*`` variables.
        wait_ready: wait for ``/readyz`` 200 (else only for ``/healthz`` 200).
        start_timeout_s: give up (and kill the child) after this long.
        log_path: where the child's stdout/stderr go (default: discarded).
    """

    def __init__(
        self,
        port: int,
        settings: dict[str, object] | None = None,
        wait_ready: bool = True,
        start_timeout_s: float = 60.0,
        log_path: Path | None = None,
    ) -> None:
        self.port = port
        self.url = f"http://127.0.0.1:{port}"
        self._settings = settings or {}
        self._wait_ready = wait_ready
        self._start_timeout_s = start_timeout_s
        self._log_path = log_path
        self._log_file = None
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def pid(self) -> int:
        """Process id of the running service."""
        if self.process is None:
            raise ServiceError("the depth service is not running; use ServiceProcess as a context manager")
        return self.process.pid

    def __enter__(self) -> "ServiceProcess":
        env = dict(os.environ)
        env.update({f"DEPTH_{k.upper()}": str(v) for k, v in self._settings.items()})
        env.setdefault("DEPTH_LOG_LEVEL", "warning")
        command = [sys.executable, "-m", "metricslam_cli.main", "depth-service",
                   "--host", "127.0.0.1", "--port", str(self.port)]
        self._log_file = open(self._log_path, "wb") if self._log_path else subprocess.DEVNULL
        self.process = subprocess.Popen(command, env=env, stdout=self._log_file, stderr=subprocess.STDOUT)
        try:
            self._wait()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _wait(self) -> None:
        probe = "/readyz" if self._wait_ready else "/healthz"
        deadline = time.monotonic() + self._start_timeout_s
        with httpx.Client(timeout=2.0) as client:
            while time.monotonic() < deadline:
                assert self.process is not None
                if self.process.poll() is not None:
                    raise ServiceError(
                        f"depth service on port {self.port} exited with code {self.process.returncode} "
                        "during start-up; run `metricslam depth-service` by hand to see why"
                    )
                try:
                    if client.get(self.url + probe).status_code == 200:
                        return
                except httpx.TransportError:
                    pass
                time.sleep(0.1)
        raise ServiceError(
            f"depth service on port {self.port} did not answer {probe} with 200 within "
            f"{self._start_timeout_s} s; is the port free and the model loadable?"
        )

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        if self._log_file not in (None, subprocess.DEVNULL):
            self._log_file.close()  # type: ignore[union-attr]
