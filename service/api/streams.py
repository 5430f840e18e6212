"""A cap on open event streams (GET /jobs/{id}/events), per client address and in all: each
open stream polls the job store four times a second, and hundreds of them stalled every other
request (400 streams: up to 4.8 s). Beyond the client's share: 429; beyond the server's: 503; both with
Retry-After. Per address, not per token: one token is usually shared by every client.
(Behind a reverse proxy every client has the proxy's address unless uvicorn trusts its
X-Forwarded-For, `--forwarded-allow-ips`.)"""
from __future__ import annotations

from collections import Counter

from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

MAX_STREAMS_PER_CLIENT = 8  # the page follows 2 jobs at once (page/feed.js)
MAX_STREAMS = 64
RETRY_AFTER_SECONDS = "5"
EVENTS_SUFFIX = "/events"


def is_event_stream(scope: Scope) -> bool:
    return scope["type"] == "http" and scope["method"] == "GET" and scope["path"].endswith(EVENTS_SUFFIX)


class StreamCap:
    """Pure ASGI middleware counting event streams while their responses are open. The event
    loop is single-threaded, so the counter needs no lock."""

    def __init__(self, app: ASGIApp, per_client: int = MAX_STREAMS_PER_CLIENT, total: int = MAX_STREAMS) -> None:
        self.app = app
        self.per_client = per_client
        self.total = total
        self.open: Counter[str] = Counter()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if not is_event_stream(scope):
            await self.app(scope, receive, send)
            return
        client = (scope.get("client") or ("unknown",))[0]
        refusal = self._refusal(client)
        if refusal is not None:
            await refusal(scope, receive, send)
            return
        self.open[client] += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.open[client] -= 1
            if self.open[client] <= 0:
                del self.open[client]

    def _refusal(self, client: str) -> JSONResponse | None:
        if self.open[client] >= self.per_client:
            return JSONResponse({"detail": f"this client has {self.open[client]} event streams open, the most "
                                           "allowed (serve --max-event-streams); close one first"},
                                status_code=429, headers={"Retry-After": RETRY_AFTER_SECONDS})
        if sum(self.open.values()) >= self.total:
            return JSONResponse({"detail": f"the server has {self.total} event streams open, its most; poll "
                                           "GET /jobs/{id} instead or retry later"},
                                status_code=503, headers={"Retry-After": RETRY_AFTER_SECONDS})
        return None
