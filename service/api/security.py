"""Who may talk to the service, and from where: a bearer token on every endpoint but
/healthz and the page's static files, a Host allow-list (a DNS-rebinding page reaches 127.0.0.1 under its own name), JSON
bodies only as `application/json` (a cross-site form can send `text/plain` without a CORS
preflight), and CORS closed unless origins are named. docs/security.md has the threat model."""
from __future__ import annotations

import hmac
import os
from dataclasses import dataclass
from urllib.parse import parse_qs

from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

TOKEN_ENV = "RENDERLOOP_TOKEN"
ALLOWED_HOSTS_ENV = "RENDERLOOP_ALLOWED_HOSTS"
CORS_ORIGINS_ENV = "RENDERLOOP_CORS_ORIGINS"
LOOPBACK_HOSTS = ("localhost", "127.0.0.1", "::1")
# The page and its static files carry no secret and must load before anyone has typed a
# token (service/api/page.py); every API call the page makes is guarded as usual.
OPEN_PATHS = frozenset({"/healthz", "/"})
OPEN_PREFIXES = ("/page/",)
# Browser elements that cannot send headers (EventSource, <img>) may carry the token in the
# query string, on these read-only GET routes only.
QUERY_TOKEN_SUFFIXES = ("/events", "/preview")
BODY_TYPES = ("application/json", "multipart/form-data")


def is_open(path: str) -> bool:
    """Paths served without a token: the health check and the page (never the API)."""
    return path in OPEN_PATHS or path.startswith(OPEN_PREFIXES)


def is_loopback(host: str) -> bool:
    return host in LOOPBACK_HOSTS or host.startswith("127.")


@dataclass(frozen=True)
class SecuritySettings:
    token: str | None = None
    allowed_hosts: tuple[str, ...] = LOOPBACK_HOSTS  # "*" allows any Host header
    cors_origins: tuple[str, ...] = ()

    @classmethod
    def from_env(cls) -> "SecuritySettings":
        hosts = tuple(h.strip() for h in os.environ.get(ALLOWED_HOSTS_ENV, "").split(",") if h.strip())
        origins = tuple(o.strip() for o in os.environ.get(CORS_ORIGINS_ENV, "").split(",") if o.strip())
        return cls(token=os.environ.get(TOKEN_ENV) or None, allowed_hosts=LOOPBACK_HOSTS + hosts, cors_origins=origins)


def _host_name(header: str) -> str:
    """`example.com:8000` → `example.com`; `[::1]:8000` → `::1`."""
    header = header.strip().lower()
    if header.startswith("["):
        return header[1:header.find("]")] if "]" in header else header
    return header.rsplit(":", 1)[0] if header.count(":") == 1 else header


def _refuse(status: int, detail: str, headers: dict | None = None) -> JSONResponse:
    return JSONResponse({"detail": detail}, status_code=status, headers=headers)


class RequestGuard:
    """Pure ASGI middleware applying SecuritySettings before any route runs."""

    def __init__(self, app: ASGIApp, settings: SecuritySettings) -> None:
        self.app = app
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        response = self._check(scope)
        if response is not None:
            await response(scope, receive, send)
            return
        await self.app(scope, receive, send)

    def _check(self, scope: Scope) -> JSONResponse | None:
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        host = _host_name(headers.get("host", ""))
        allowed = self.settings.allowed_hosts
        if "*" not in allowed and host not in allowed:
            return _refuse(400, f"Host {host!r} is not served here; start the server with --allowed-host {host} "
                                "to allow it")
        method, path = scope["method"], scope["path"]
        if method == "OPTIONS":
            return None  # CORS preflight: answered (or refused) by the CORS middleware
        if self.settings.token is not None and not is_open(path) and not self._authorised(scope, headers):
            return _refuse(401, "this server needs a token: send 'Authorization: Bearer <token>'",
                           {"WWW-Authenticate": "Bearer"})
        if method in ("POST", "PUT", "PATCH") and _has_body(headers):
            media_type = headers.get("content-type", "").split(";", 1)[0].strip().lower()
            if media_type not in BODY_TYPES:
                return _refuse(415, f"send JSON as 'application/json' or uploads as 'multipart/form-data', "
                                    f"not {media_type or 'no content type'!r}")
        return None

    def _authorised(self, scope: Scope, headers: dict[str, str]) -> bool:
        expected = self.settings.token.encode()
        scheme, _, given = headers.get("authorization", "").partition(" ")
        if scheme.lower() == "bearer" and hmac.compare_digest(given.strip().encode(), expected):
            return True
        if scope["method"] == "GET" and scope["path"].endswith(QUERY_TOKEN_SUFFIXES):
            query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
            return any(hmac.compare_digest(value.encode(), expected) for value in query.get("token", []))
        return False


def _has_body(headers: dict[str, str]) -> bool:
    length = headers.get("content-length")
    return "transfer-encoding" in headers or (length is not None and length.strip() not in ("", "0"))
