"""Bounded admission of CPU work: a fixed worker pool, a bounded wait queue, explicit refusals.

Policy (stated once, here):

* at most ``max_concurrency`` jobs run at once, each on a worker thread (never on the event loop);
* up to ``max_queue`` more requests may wait for a slot; one more is refused at once with
  **429** (``Retry-After``) — the caller should back off;
* a request that waited ``timeout_s`` without getting a slot is refused with **503**
  (``Retry-After``) — the service is saturated, latency stays bounded instead of growing.

A slot is released when its job *finishes* (not when its request goes away), so an abandoned
request can never let more than ``max_concurrency`` jobs pile onto the CPU.

In front of the gate, :class:`InflightLimit` caps the HTTP requests alive at once (bodies being
received included), exempting the liveness/readiness probes.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from starlette.types import ASGIApp, Receive, Scope, Send

from .errors import RequestProblem, problem_response
from .metrics import ServiceMetrics

T = TypeVar("T")


class AdmissionGate:
    """Runs blocking callables on a bounded pool with a bounded, time-limited wait queue.

    Args:
        max_concurrency: worker threads (jobs running at once).
        max_queue: requests allowed to wait for a worker.
        timeout_s: longest wait for a worker before 503.
        retry_after_s: value of the ``Retry-After`` header on refusals (seconds).
        metrics: gauges/counters to update (queue depth, in flight, rejections).
    """

    def __init__(
        self,
        max_concurrency: int,
        max_queue: int,
        timeout_s: float,
        retry_after_s: int,
        metrics: ServiceMetrics,
    ) -> None:
        self._max_queue = max_queue
        self._timeout_s = timeout_s
        self._retry_headers = {"Retry-After": str(retry_after_s)}
        self._metrics = metrics
        self._slots = asyncio.Semaphore(max_concurrency)
        self._waiting = 0
        self._executor = ThreadPoolExecutor(max_concurrency, thread_name_prefix="depth-infer")

    async def run(self, fn: Callable[[], T]) -> T:
        """Run ``fn()`` on a worker thread once a slot is free; return its result.

        Raises:
            RequestProblem: 429 when the queue is full, 503 after waiting ``timeout_s``.
        """
        await self._admit()
        self._metrics.inflight.inc()
        try:
            future = asyncio.get_running_loop().run_in_executor(self._executor, fn)
        except BaseException:
            self._release(None)
            raise
        future.add_done_callback(self._release)
        return await future

    async def _admit(self) -> None:
        if self._slots.locked() and self._waiting >= self._max_queue:
            self._metrics.rejected.labels("queue_full").inc()
            raise RequestProblem(
                429, "overloaded", "Too many requests queued",
                f"{self._waiting} requests are already waiting for the network (limit "
                f"{self._max_queue}); retry after the Retry-After delay, send fewer concurrent "
                "requests, or run more service instances.",
                headers=self._retry_headers,
            )
        self._waiting += 1
        self._metrics.queue_depth.set(self._waiting)
        t0 = time.perf_counter()
        try:
            async with asyncio.timeout(self._timeout_s):
                await self._slots.acquire()
        except TimeoutError:
            self._metrics.rejected.labels("queue_timeout").inc()
            raise RequestProblem(
                503, "queue-timeout", "Service saturated",
                f"no inference slot became free within {time.perf_counter() - t0:.1f} s "
                f"(limit {self._timeout_s} s); retry after the Retry-After delay or lower the "
                "request rate.",
                headers=self._retry_headers,
            ) from None
        finally:
            self._waiting -= 1
            self._metrics.queue_depth.set(self._waiting)

    def _release(self, _future: object) -> None:
        self._metrics.inflight.dec()
        self._slots.release()

    def shutdown(self) -> None:
        """Stop the worker threads after the jobs already submitted."""
        self._executor.shutdown(wait=True, cancel_futures=True)


class InflightLimit:
    """Pure ASGI middleware: at most ``max_requests`` HTTP requests received or served at once.

    Counts requests, not connections — an idle keep-alive connection costs nothing here (idle
    connections are :mod:`metricslam_depth.connections`' business). Liveness and readiness
    probes (``exempt_paths``) are never refused: they are answered from memory in microseconds,
    and their number is bounded by the connection cap anyway. Beyond the limit: 503
    ``busy`` with ``Retry-After`` and ``Connection: close`` (the body is never read).

    Args:
        app: the wrapped ASGI app.
        max_requests: requests allowed at once.
        exempt_paths: paths never refused (``/healthz``, ``/readyz``).
        retry_after_s: ``Retry-After`` on the 503.
        metrics: ``depth_rejected_total{reason="busy"}``.
    """

    def __init__(
        self, app: ASGIApp, max_requests: int, exempt_paths: frozenset[str], retry_after_s: int,
        metrics: ServiceMetrics,
    ) -> None:
        self.app = app
        self._max_requests = max_requests
        self._exempt_paths = exempt_paths
        self._headers = {"Retry-After": str(retry_after_s), "Connection": "close"}
        self._metrics = metrics
        self._inflight = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope.get("path") in self._exempt_paths:
            await self.app(scope, receive, send)
            return
        if self._inflight >= self._max_requests:
            self._metrics.rejected.labels("busy").inc()
            response = problem_response(
                503, "busy", "Service busy",
                f"{self._inflight} requests are already being received or served (limit "
                f"{self._max_requests}); retry after the Retry-After delay.",
                scope.get("path", ""), headers=self._headers,
            )
            await response(scope, receive, send)
            return
        self._inflight += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self._inflight -= 1
