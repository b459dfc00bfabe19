"""Liveness of the supervised stack: does each child still *answer*, not merely exist?

A process that is alive but hung (stopped, deadlocked, stuck in a call) keeps its pid and its
listening sockets — the kernel even completes TCP handshakes for it — so ``poll()`` and a port
check both call it healthy. The :class:`LivenessMonitor` instead asks each child the question
its users ask, every ``period_s`` on its own thread, and remembers when it last answered:

* zenoh router: the queryable ``metricslam/_router/health`` that :mod:`.router` answers itself;
* depth service: ``GET /healthz`` (exempt from its request caps, so load does not fail it);
* SLAM service: the queryable ``metricslam/_service/health``.

The SLAM service is reached through the router, so while the router does not answer its probe
says nothing about the SLAM service, which then counts as answering (the router is the one to
restart). The launcher (:class:`~metricslam_slam.supervisor.launcher.Stack`) kills a child that
has not answered for ``hang_timeout_s`` and restarts it with its usual backoff.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Callable

import httpx
import zenoh

from metricslam.errors import ServiceError
from metricslam.wire import keys

log = logging.getLogger(__name__)
Probe = Callable[[], bool]


def http_healthz(url: str, timeout_s: float) -> bool:
    """``GET {url}/healthz`` answers 200 within ``timeout_s``."""
    try:
        return httpx.get(f"{url}/healthz", timeout=timeout_s).status_code == 200
    except httpx.HTTPError:
        return False


class ZenohProbe:
    """One client session to the router for the probes (opened lazily; zenoh reconnects it after
    a router restart by itself).

    Args:
        endpoint: the router's endpoint.
        timeout_s: how long one query waits for its answer.
    """

    def __init__(self, endpoint: str, timeout_s: float) -> None:
        self.endpoint = endpoint
        self.timeout_s = timeout_s
        self._session: zenoh.Session | None = None
        self._lock = threading.Lock()

    def _query(self, key: str) -> dict | None:
        with self._lock:
            if self._session is None:
                from metricslam_slam.zenoh_config import open_client

                try:
                    self._session = open_client(self.endpoint)
                except ServiceError:
                    return None
            session = self._session
        try:
            for reply in session.get(key, timeout=self.timeout_s):
                if reply.ok is not None:
                    return json.loads(reply.ok.payload.to_bytes())
        except (zenoh.ZError, ValueError):
            return None
        return None

    def router(self) -> bool:
        """The router answered its own health queryable."""
        return self._query(keys.ROUTER_HEALTH_KEY) is not None

    def slam(self) -> bool:
        """A SLAM service answered its health queryable, ready."""
        health = self._query(keys.HEALTH_KEY)
        return bool(health and health.get("ready"))

    def close(self) -> None:
        with self._lock:
            if self._session is not None:
                self._session.close()
                self._session = None


class LivenessMonitor:
    """Probes children on a thread and records ``child.last_answer_s`` (``time.monotonic()``).

    Args:
        children: objects with ``name``, ``probe`` (a :data:`Probe` or None: not probed),
            ``alive()`` and a writable ``last_answer_s``.
        period_s: time between probe rounds.
        gate: ``{child name: name of the child its probe goes through}``; while the gate does
            not answer, the gated child counts as answering (the gate is the one to blame).
    """

    def __init__(self, children: list, period_s: float, gate: dict[str, str] | None = None) -> None:
        self.children = children
        self.period_s = period_s
        self.gate = dict(gate or {})
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> "LivenessMonitor":
        self._thread = threading.Thread(target=self._run, name="liveness", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)

    def probe_once(self) -> dict[str, bool]:
        """One round: probe every living child that has a probe; returns name -> answered."""
        answered: dict[str, bool] = {}
        for child in self.children:
            if child.probe is None:
                continue
            if not child.alive():  # being restarted: it answers nothing, nor does what it gates
                answered[child.name] = False
                continue
            gate = self.gate.get(child.name)
            if gate is not None and answered.get(gate) is False:
                ok = True  # unreachable behind a silent gate: no evidence against it
            else:
                try:
                    ok = bool(child.probe())
                except Exception:  # noqa: BLE001 -- a probe that fails is a child that did not answer
                    log.debug("liveness probe of %s raised", child.name, exc_info=True)
                    ok = False
            answered[child.name] = ok
            if ok:
                child.last_answer_s = time.monotonic()
        return answered

    def _run(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            self.probe_once()
            self._stop.wait(max(self.period_s - (time.monotonic() - t0), 0.05))

