"""Connection guards below the ASGI app: idle and slow connections cannot starve the service.

uvicorn alone (``limit_concurrency``) counts every open connection, idle or not, and never times
out a connection that opened and sent nothing: 256 idle sockets made every request — health
included — a 503 for as long as they stayed open. This protocol (uvicorn's httptools protocol
plus three rules) replaces that:

* **request-head deadline** — a connection must deliver a complete request line + headers
  within ``header_timeout_s`` of opening (or of the first byte of its next request); otherwise
  it is closed. Idle keep-alive connections are closed after ``keep_alive_timeout_s`` by uvicorn.
* **head size** — more than ``max_header_bytes`` of request line + headers: 431, closed.
* **connection cap without starvation** — when ``max_connections`` are open, a new connection
  closes the connection that has been idle (no request running) the longest, so a fresh client
  (a health probe, a real request) always gets in while idle sockets are what is dropped. Only
  when every open connection is running a request is the newcomer refused (503, closed).

Admission of *requests* (not connections) is :class:`metricslam_depth.admission.InflightLimit`.
"""

from __future__ import annotations

import asyncio
import json
import logging
from dataclasses import dataclass
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

log = logging.getLogger(__name__)

_REASONS = {431: b"Request Header Fields Too Large", 503: b"Service Unavailable"}


@dataclass(frozen=True)
class ConnectionLimits:
    """The connection rules (fields as in :class:`~metricslam_depth.settings.DepthServiceSettings`)."""

    max_connections: int
    header_timeout_s: float
    max_header_bytes: int
    retry_after_s: int


def _problem_bytes(status: int, code: str, detail: str, headers: dict[str, str]) -> bytes:
    """A complete ``Connection: close`` HTTP/1.1 response with a problem body (see errors.py)."""
    body = json.dumps({
        "type": f"urn:metricslam:problem:{code}", "code": code,
        "title": _REASONS[status].decode(), "status": status, "detail": detail, "instance": "",
    }).encode()
    lines = [b"HTTP/1.1 %d %s" % (status, _REASONS[status]),
             b"content-type: application/problem+json",
             b"content-length: %d" % len(body), b"connection: close"]
    lines += [f"{k}: {v}".encode("latin-1") for k, v in headers.items()]
    return b"\r\n".join(lines) + b"\r\n\r\n" + body


class IdleConnections:
    """The server's connections that run no request, longest idle first (one per server).

    Insertion-ordered: a connection is (re)appended when it opens or finishes a response and
    removed when a request head completes or it closes, so the first entry is always the one
    to evict, found in O(1) however many connections are open.
    """

    def __init__(self) -> None:
        self._order: dict[GuardedHttpProtocol, None] = {}

    def mark_idle(self, connection: GuardedHttpProtocol) -> None:
        self._order.pop(connection, None)
        self._order[connection] = None

    def mark_busy(self, connection: GuardedHttpProtocol) -> None:
        self._order.pop(connection, None)

    def pop_longest_idle(self) -> GuardedHttpProtocol | None:
        for connection in self._order:
            del self._order[connection]
            return connection
        return None


class GuardedHttpProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with the rules of the module doc; one instance per connection.

    Built by uvicorn through ``functools.partial(GuardedHttpProtocol, limits=..., idle=...)``
    (see :func:`metricslam_depth.server.serve`).
    """

    def __init__(self, *args: Any, limits: ConnectionLimits, idle: IdleConnections, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._limits = limits
        self._idle = idle
        self._head_timer: asyncio.TimerHandle | None = None
        self._in_head = True  # receiving a request line + headers (or waiting for one)
        self._head_bytes = 0  # bytes received while in the head (catches heads that never end)
        self._parsed_head_bytes = 0  # request line + headers as parsed (catches whole huge heads)
        self._refused = False

    # ----- connection life -----

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        crowded = len(self.connections) >= self._limits.max_connections
        super().connection_made(transport)
        if crowded and not self._evict_longest_idle():
            log.warning("all %d connections are busy; refusing a new one", self._limits.max_connections)
            self._refuse(503, "too-many-connections",
                         f"all {self._limits.max_connections} connections are running requests; "
                         "retry after the Retry-After delay.",
                         {"retry-after": str(self._limits.retry_after_s)})
            return
        self._idle.mark_idle(self)
        self._arm_head_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        self._idle.mark_busy(self)
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._refused:
            return
        if self._in_head:
            self._head_bytes += len(data)
        super().data_received(data)
        # a head still incomplete after this much data (the parser reports headers only whole)
        if self._in_head and self._head_bytes > self._limits.max_header_bytes and not self._refused:
            self._refuse_large_head()

    def send_400_response(self, msg: str) -> None:
        if not self._refused:  # after a refusal the parser may still complain: nothing to add
            super().send_400_response(msg)

    def _refuse_large_head(self) -> None:
        self._refuse(431, "header-too-large",
                     f"the request line and headers are larger than {self._limits.max_header_bytes} "
                     "bytes; send fewer or shorter headers.", {})

    def _evict_longest_idle(self) -> bool:
        victim = self._idle.pop_longest_idle()
        if victim is None:
            return False
        victim._refused = True
        victim._cancel_head_timer()
        victim.transport.close()
        return True

    def _refuse(self, status: int, code: str, detail: str, headers: dict[str, str]) -> None:
        self._refused = True
        self._idle.mark_busy(self)
        self._cancel_head_timer()
        if not self.transport.is_closing():
            self.transport.write(_problem_bytes(status, code, detail, headers))
            self.transport.close()

    # ----- request head deadline -----

    def _arm_head_timer(self) -> None:
        if self._head_timer is None:
            self._head_timer = self.loop.call_later(self._limits.header_timeout_s, self._head_timeout)

    def _cancel_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_timeout(self) -> None:
        self._head_timer = None
        if self._in_head and not self.transport.is_closing():
            self._refused = True
            self._idle.mark_busy(self)
            self.transport.close()  # no response: the client never sent a request to answer

    # ----- parser callbacks (httptools) -----

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._in_head = True
        self._parsed_head_bytes = 0
        self._arm_head_timer()

    def on_url(self, url: bytes) -> None:
        self._parsed_head_bytes += len(url)
        super().on_url(url)

    def on_header(self, name: bytes, value: bytes) -> None:
        self._parsed_head_bytes += len(name) + len(value) + 4
        super().on_header(name, value)

    def on_headers_complete(self) -> None:
        self._in_head = False
        self._head_bytes = 0
        self._cancel_head_timer()
        if self._refused:
            return
        if self._parsed_head_bytes > self._limits.max_header_bytes:  # the whole head in one read
            self._refuse_large_head()
            return
        self._idle.mark_busy(self)
        super().on_headers_complete()

    def on_body(self, body: bytes) -> None:
        if not self._refused:
            super().on_body(body)

    def on_message_complete(self) -> None:
        if self._refused:
            return
        super().on_message_complete()
        self._in_head = True  # what follows is the next request's head
        self._head_bytes = 0

    def on_response_complete(self) -> None:
        pipelined = bool(self.pipeline)  # uvicorn starts the next queued request right away
        super().on_response_complete()
        if not pipelined and not self.transport.is_closing() and not self._refused:
            self._idle.mark_idle(self)
