"""Who may talk to the service, and from where: a bearer token on every endpoint but
/healthz and the page's static files (previews and event streams also take a short-lived signed
URL, service.api.signing), a Host allow-list (a DNS-rebinding page reaches 127.0.0.1 under its
own name), state-changing requests only from the server's own origin or a `--cors-origin`
(a cross-site multipart form needs no CORS preflight), JSON bodies only as `application/json`
(a cross-site form can send `text/plain` without a preflight), CORS closed unless origins are
named, and a cap on open event streams (service.api.streams). docs/security.md has the
threat model."""
from __future__ import annotations

import hmac
import os
import stat
import sys
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from service.api.links import SIGNER_STATE
from service.api.signing import UrlSigner, signed_job_id
from service.api.streams import MAX_STREAMS, MAX_STREAMS_PER_CLIENT, StreamCap

TOKEN_ENV = "RENDERLOOP_TOKEN"
TOKEN_FILE_ENV = "RENDERLOOP_TOKEN_FILE"
MAX_TOKEN_FILE_BYTES = 4096
MAX_STREAMS_ENV = "RENDERLOOP_MAX_EVENT_STREAMS"  # per client address
ALLOWED_HOSTS_ENV = "RENDERLOOP_ALLOWED_HOSTS"
CORS_ORIGINS_ENV = "RENDERLOOP_CORS_ORIGINS"
LOOPBACK_HOSTS = ("localhost", "127.0.0.1", "::1")
# The page and its static files carry no secret and must load before anyone has typed a
# token (service/api/page.py); every API call the page makes is guarded as usual.
OPEN_PATHS = frozenset({"/healthz", "/"})
OPEN_PREFIXES = ("/page/",)
BODY_TYPES = ("application/json", "multipart/form-data")
STATE_CHANGING = frozenset({"POST", "PUT", "PATCH", "DELETE"})
# What a browser's Sec-Fetch-Site says about a request this server's own page made (or one
# typed into the address bar); `same-site` is another port or subdomain, i.e. another origin.
OWN_SITE = frozenset({"same-origin", "none"})
DEFAULT_PORTS = {"http": "80", "https": "443"}


class TokenFileError(ValueError):
    """--token-file names no readable, non-empty, small file."""


def read_token_file(path: Path) -> str:
    """The token from its file (surrounding whitespace stripped). Warns when other users may
    read the file: the point of a token file is that only the server's user sees the token."""
    try:
        mode = path.stat().st_mode
        if not stat.S_ISREG(mode) or path.stat().st_size > MAX_TOKEN_FILE_BYTES:
            raise TokenFileError(f"token file {str(path)!r} is not a regular file of at most {MAX_TOKEN_FILE_BYTES} bytes")
        token = path.read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise TokenFileError(f"cannot read the token file {str(path)!r}: {exc}") from exc
    if not token:
        raise TokenFileError(f"token file {str(path)!r} is empty")
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        print(f"renderloop: warning: token file {str(path)!r} is readable by other users; chmod 600 it",
              file=sys.stderr)
    return token


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
    max_streams_per_client: int = MAX_STREAMS_PER_CLIENT
    max_streams: int = MAX_STREAMS
    url_signer: UrlSigner | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.token is not None and self.url_signer is None:
            object.__setattr__(self, "url_signer", UrlSigner.from_token(self.token))

    @classmethod
    def from_env(cls) -> "SecuritySettings":
        hosts = tuple(h.strip() for h in os.environ.get(ALLOWED_HOSTS_ENV, "").split(",") if h.strip())
        origins = tuple(o.strip() for o in os.environ.get(CORS_ORIGINS_ENV, "").split(",") if o.strip())
        token_file = os.environ.get(TOKEN_FILE_ENV)
        token = read_token_file(Path(token_file)) if token_file else os.environ.get(TOKEN_ENV) or None
        streams = os.environ.get(MAX_STREAMS_ENV)
        return cls(token=token, allowed_hosts=LOOPBACK_HOSTS + hosts, cors_origins=origins,
                   max_streams_per_client=int(streams) if streams else MAX_STREAMS_PER_CLIENT)


def _host_name(header: str) -> str:
    """`example.com:8000` → `example.com`; `[::1]:8000` → `::1`."""
    header = header.strip().lower()
    if header.startswith("["):
        return header[1:header.find("]")] if "]" in header else header
    return header.rsplit(":", 1)[0] if header.count(":") == 1 else header


def _origin(value: str) -> str:
    """`HTTPS://Example.com:443/` → `https://example.com`: the form browsers send, compared as such."""
    parts = urlsplit(value.strip().lower())
    try:
        port = parts.port
    except ValueError:
        return value.strip().lower()  # no valid port: compared as written, so it matches nothing real
    host = parts.netloc.rsplit(":", 1)[0] if port is not None else parts.netloc
    if port is None or str(port) == DEFAULT_PORTS.get(parts.scheme):
        return f"{parts.scheme}://{host}"
    return f"{parts.scheme}://{host}:{port}"


def _refuse(status: int, detail: str, headers: dict | None = None) -> JSONResponse:
    return JSONResponse({"detail": detail}, status_code=status, headers=headers)


class RequestGuard:
    """Pure ASGI middleware applying SecuritySettings before any route runs."""

    def __init__(self, app: ASGIApp, settings: SecuritySettings) -> None:
        # Streams are counted behind the guard: a refused request never holds a slot.
        self.app = StreamCap(app, settings.max_streams_per_client, settings.max_streams)
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        response = self._check(scope)
        # GET /jobs/{id}/links signs with the same key the guard verifies (service.api.links).
        scope.setdefault("state", {})[SIGNER_STATE] = self.settings.url_signer
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
        if method in STATE_CHANGING:
            refusal = self._cross_site(scope, headers)
            if refusal is not None:
                return refusal
        if self.settings.token is not None and not is_open(path) and not self._authorised(scope, headers):
            return _refuse(401, _why_unauthorised(scope), {"WWW-Authenticate": "Bearer"})
        if method in ("POST", "PUT", "PATCH") and _has_body(headers):
            media_type = headers.get("content-type", "").split(";", 1)[0].strip().lower()
            if media_type not in BODY_TYPES:
                return _refuse(415, f"send JSON as 'application/json' or uploads as 'multipart/form-data', "
                                    f"not {media_type or 'no content type'!r}")
        return None

    def _cross_site(self, scope: Scope, headers: dict[str, str]) -> JSONResponse | None:
        """403 for a browser request from another web origin. Browsers send `Origin` on every
        request that is not GET/HEAD; clients that are not browsers (curl, service.client)
        send neither it nor Sec-Fetch-*, and pass."""
        origin = headers.get("origin")
        if origin is None:
            site = headers.get("sec-fetch-site", "").strip().lower()
            if not site or site in OWN_SITE:
                return None
            return _refuse(403, f"a cross-site browser request (Sec-Fetch-Site: {site}) may not change anything "
                                "here; only this server's page and the origins named by --cors-origin may")
        own = _origin(f"{scope.get('scheme', 'http')}://{headers.get('host', '')}")
        if _origin(origin) == own or _origin(origin) in {_origin(o) for o in self.settings.cors_origins}:
            return None
        return _refuse(403, f"requests from the web origin {origin!r} may not change anything here; only this "
                            f"server's own page may, and origins named by --cors-origin (e.g. --cors-origin {origin})")

    def _authorised(self, scope: Scope, headers: dict[str, str]) -> bool:
        expected = self.settings.token.encode()
        scheme, _, given = headers.get("authorization", "").partition(" ")
        if scheme.lower() == "bearer" and hmac.compare_digest(given.strip().encode(), expected):
            return True
        job_id = signed_job_id(scope["path"]) if scope["method"] in ("GET", "HEAD") else None
        if job_id is None or self.settings.url_signer is None:
            return False
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        expires, signature = query.get("exp", [""])[-1], query.get("sig", [""])[-1]
        return self.settings.url_signer.verify(job_id, expires, signature)


def _why_unauthorised(scope: Scope) -> str:
    job_id = signed_job_id(scope["path"])
    query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
    if job_id is not None and "token" in query:
        return (f"the token is not accepted in a URL (logs and browser history keep URLs): send 'Authorization: "
                f"Bearer <token>', or use the signed URL from GET /jobs/{job_id}/links")
    if job_id is not None and "sig" in query:
        return f"this signed URL has expired or is not valid: GET /jobs/{job_id}/links gives a fresh one"
    return "this server needs a token: send 'Authorization: Bearer <token>'"


def _has_body(headers: dict[str, str]) -> bool:
    length = headers.get("content-length")
    return "transfer-encoding" in headers or (length is not None and length.strip() not in ("", "0"))
