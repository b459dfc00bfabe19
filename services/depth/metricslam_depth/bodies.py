"""Request bodies: judged before they are buffered, received under a deadline and a memory budget.

Policy (stated once, here):

* a declared ``Content-Length`` over the endpoint's limit is refused (413) before one body byte
  is read; without one (chunked upload) the limit is enforced while the bytes stream in;
* before reading, a request reserves the bytes it may hold — its ``Content-Length``, or the
  endpoint's limit when none is declared — from one budget shared by all requests
  (``max_buffered_body_bytes``); while the budget is spent it waits up to ``wait_s`` for other
  requests to finish, then gets 503 with ``Retry-After``. Unread bytes stay in the kernel
  (uvicorn stops reading a connection once 64 KiB are pending), so memory is bounded by the
  budget, not by the number of uploaders;
* the whole body must arrive within ``body_timeout_s`` (else 408): a slow sender cannot hold a
  reservation and a connection forever;
* a refusal before the body has been read answers ``Connection: close``, so the server never
  reads (and throws away) the rest of an oversized upload.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

from starlette.requests import ClientDisconnect, Request

from .errors import RequestProblem
from .metrics import ServiceMetrics

CLOSE = {"Connection": "close"}


def too_large(limit_bytes: int, what: str, setting: str = "DEPTH_MAX_BODY_BYTES") -> RequestProblem:
    """413 ``body-too-large`` for ``what`` over ``limit_bytes`` (closes the connection)."""
    return RequestProblem(
        413, "body-too-large", "Request body too large",
        f"the {what} is larger than the limit of {limit_bytes} bytes; send a smaller (downscaled or "
        f"JPEG) image, or raise {setting} on the server.",
        headers=dict(CLOSE),
    )


def declared_length(request: Request, limit_bytes: int, what: str) -> int | None:
    """The request's ``Content-Length`` (``None`` if absent); 413 at once if over ``limit_bytes``."""
    declared = request.headers.get("content-length")
    if declared is None or not declared.isdigit():
        return None
    if int(declared) > limit_bytes:
        raise too_large(limit_bytes, what)
    return int(declared)


async def receive(
    request: Request, limit_bytes: int, what: str, timeout_s: float, sink: Callable[[bytes], None]
) -> int:
    """Stream the body into ``sink`` chunk by chunk; return its size in bytes.

    ``sink`` may raise :class:`RequestProblem` to refuse the body part-way (e.g. one batch image
    too large); the refusal then closes the connection like any other here.

    Raises:
        RequestProblem: 413 over ``limit_bytes``, 408 after ``timeout_s``, 400 when the client
            disconnects before the end.
    """
    size = 0
    try:
        async with asyncio.timeout(timeout_s):
            async for chunk in request.stream():
                size += len(chunk)
                if size > limit_bytes:
                    raise too_large(limit_bytes, what)
                if chunk:
                    sink(chunk)
    except TimeoutError:
        raise RequestProblem(
            408, "body-timeout", "Request body too slow",
            f"the {what} did not arrive within {timeout_s} s ({size} bytes received); send it "
            "faster, or smaller.",
            headers=dict(CLOSE),
        ) from None
    except ClientDisconnect:
        raise RequestProblem(
            400, "incomplete-body", "Request body incomplete",
            f"the connection closed after {size} bytes of the {what}; send the whole body.",
        ) from None
    except RequestProblem as exc:
        exc.headers.update(CLOSE)
        raise
    return size


class BodyBudget:
    """Bytes of request bodies all requests together may hold in memory (see module doc).

    A FIFO byte semaphore: reservations are granted in arrival order (a large upload is not
    starved by a stream of small ones), and released synchronously, so a cancelled request can
    never leak its share.

    Args:
        capacity_bytes: the budget.
        wait_s: longest wait for a reservation before 503.
        retry_after_s: ``Retry-After`` on that 503.
        metrics: ``depth_rejected_total{reason="body_budget"}`` and the reserved-bytes gauge.
    """

    def __init__(self, capacity_bytes: int, wait_s: float, retry_after_s: int, metrics: ServiceMetrics) -> None:
        self.capacity_bytes = capacity_bytes
        self._available_bytes = capacity_bytes
        self._wait_s = wait_s
        self._retry_after_s = retry_after_s
        self._metrics = metrics
        self._waiters: deque[tuple[int, asyncio.Future[None]]] = deque()

    @asynccontextmanager
    async def reserve(self, nbytes: int) -> AsyncIterator[None]:
        """Hold ``nbytes`` of the budget for the ``async with`` block.

        Raises:
            RequestProblem: 503 ``upload-budget`` when ``nbytes`` did not become free in time.
        """
        nbytes = min(nbytes, self.capacity_bytes)
        t0 = time.perf_counter()
        try:
            async with asyncio.timeout(self._wait_s):
                await self._acquire(nbytes)
        except TimeoutError:
            self._metrics.rejected.labels("body_budget").inc()
            raise RequestProblem(
                503, "upload-budget", "Too many uploads in progress",
                f"other uploads hold the server's upload memory ({self.capacity_bytes} bytes) and "
                f"{nbytes} bytes did not become free within {time.perf_counter() - t0:.1f} s; retry "
                "after the Retry-After delay or send fewer large uploads at once.",
                headers={"Retry-After": str(self._retry_after_s), **CLOSE},
            ) from None
        try:
            yield
        finally:
            self._release(nbytes)

    async def _acquire(self, nbytes: int) -> None:
        if not self._waiters and self._available_bytes >= nbytes:
            self._take(nbytes)
            return
        granted: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._waiters.append((nbytes, granted))
        try:
            await granted
        except BaseException:
            if granted.done() and not granted.cancelled():
                self._release(nbytes)  # granted just as the wait was cancelled: give it back
            else:
                self._wake()  # let the waiters behind this one go first
            raise

    def _take(self, nbytes: int) -> None:
        self._available_bytes -= nbytes
        self._metrics.body_bytes_reserved.set(self.capacity_bytes - self._available_bytes)

    def _release(self, nbytes: int) -> None:
        self._available_bytes += nbytes
        self._metrics.body_bytes_reserved.set(self.capacity_bytes - self._available_bytes)
        self._wake()

    def _wake(self) -> None:
        while self._waiters:
            nbytes, granted = self._waiters[0]
            if granted.done():  # cancelled while waiting
                self._waiters.popleft()
                continue
            if nbytes > self._available_bytes:
                return
            self._waiters.popleft()
            self._take(nbytes)
            granted.set_result(None)
