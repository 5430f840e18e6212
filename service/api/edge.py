"""The HTTP edge: how uvicorn holds connections against slow clients, and what its logs
may show.

- A header deadline: uvicorn arms its keep-alive timer only after a response, so a client that
  opens a connection and trickles (or never finishes) its request headers held it forever; a
  thousand such connections ate every file descriptor. Here a connection waiting for request
  headers is closed after `header_timeout` seconds, on its first request and between requests.
- A connection cap (uvicorn's `limit_concurrency`: a request beyond it is answered 503). When a
  new connection would go over it, the connection that has waited longest for its request
  headers is closed first, so idle and half-open connections cannot starve real requests.
- Header size stays h11's default cap (16 KiB, then 400); keep-alive idles out after
  `keep_alive_timeout` seconds.
- Access log lines carry the request target; `token=` and `sig=` values in it are redacted.
"""
from __future__ import annotations

import asyncio
import copy
import logging
import re
import time
from typing import Any

import h11
from uvicorn.config import LOGGING_CONFIG
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.api.edge_settings import HEADER_TIMEOUT_SECONDS, MAX_CONNECTIONS, EdgeSettings

SECRET_QUERY = re.compile(r"(?i)((?:^|[?&;])(?:token|sig|access_token)=)[^&;\s\"]*")


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a deadline for request headers and idle-first eviction at
    the connection cap. Subclassed per server by `protocol_for` (uvicorn builds protocols
    from a class and its Config, with no room for our settings)."""

    header_timeout: float = HEADER_TIMEOUT_SECONDS
    max_connections: int = MAX_CONNECTIONS

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        self.header_deadline: asyncio.TimerHandle | None = None
        self.waiting_since = time.monotonic()
        super().connection_made(transport)
        self._arm_header_deadline()
        if len(self.connections) >= self.max_connections:  # uvicorn answers 503 from here on
            self._evict_longest_waiting()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm_header_deadline()
        super().connection_lost(exc)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_header_deadline()  # the next request's headers get the same deadline

    def awaiting_request(self) -> bool:
        """True while no request headers are complete and no response is in flight."""
        idle_cycle = self.cycle is None or self.cycle.response_complete
        return idle_cycle and self.conn.their_state in (h11.IDLE, h11.DONE) and not self.transport.is_closing()

    def _arm_header_deadline(self) -> None:
        self._disarm_header_deadline()
        self.waiting_since = time.monotonic()
        self.header_deadline = self.loop.call_later(self.header_timeout, self._header_deadline_passed)

    def _disarm_header_deadline(self) -> None:
        if getattr(self, "header_deadline", None) is not None:
            self.header_deadline.cancel()
            self.header_deadline = None

    def _header_deadline_passed(self) -> None:
        self.header_deadline = None
        if self.awaiting_request() and self.conn.their_state is h11.IDLE:
            self.transport.close()

    def _evict_longest_waiting(self) -> None:
        waiting = [c for c in self.connections
                   if c is not self and isinstance(c, GuardedH11Protocol) and c.awaiting_request()]
        if waiting:
            min(waiting, key=lambda c: c.waiting_since).transport.close()


def protocol_for(edge: EdgeSettings) -> type[GuardedH11Protocol]:
    return type("EdgeH11Protocol", (GuardedH11Protocol,),
                {"header_timeout": edge.header_timeout, "max_connections": edge.max_connections})


class RedactSecrets(logging.Filter):
    """Replaces the values of `token=` and `sig=` in a log record's arguments and message
    with `***` (uvicorn's access line prints the path with its query string)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(redact(a) if isinstance(a, str) else a for a in record.args)
        if isinstance(record.msg, str):
            record.msg = redact(record.msg)
        return True


def redact(text: str) -> str:
    return SECRET_QUERY.sub(r"\1***", text)


def logging_config() -> dict[str, Any]:
    """uvicorn's logging configuration with RedactSecrets on every handler."""
    config = copy.deepcopy(LOGGING_CONFIG)
    config["filters"] = {"redact_secrets": {"()": RedactSecrets}}
    for handler in config["handlers"].values():
        handler.setdefault("filters", []).append("redact_secrets")
    return config


def uvicorn_options(edge: EdgeSettings) -> dict[str, Any]:
    """Keyword arguments for uvicorn.run / uvicorn.Config that put the edge in place."""
    return {"http": protocol_for(edge), "timeout_keep_alive": edge.keep_alive_timeout,
            "limit_concurrency": edge.max_connections, "log_config": logging_config()}
