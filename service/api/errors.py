"""Every error leaves the API as JSON `{"detail": "<what is wrong>"}` with a 4xx status; a 500
only for a genuine bug, with a short message (the traceback goes to the log, not the client)."""
from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.lambda_map import LambdaMapError
from service.jobs.bundle import BundleError
from service.jobs.errors import JobConflict, JobNotFound, StoreUnavailable

log = logging.getLogger(__name__)


class UploadTooLarge(Exception):
    """The request body is over its route's cap (413). Not a ValueError: a JSON parser's
    `except ValueError` must not turn it into "invalid JSON"."""


def _location(loc: tuple) -> str:
    # ("body", "width") → "width"; ("query", "frame") → "frame": the field is what people need.
    parts = [str(p) for p in loc if p not in ("body", "query", "path", "header")]
    return ".".join(parts) or "body"


def validation_message(errors: list[dict]) -> str:
    return "; ".join(f"{_location(tuple(e.get('loc', ())))}: {e.get('msg', 'invalid')}" for e in errors)


def _json(status: int, detail: str, **extra) -> JSONResponse:
    return JSONResponse({"detail": detail, **extra}, status_code=status)


async def _validation(_: Request, exc: RequestValidationError) -> JSONResponse:
    errors = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", "")} for e in exc.errors()]
    return _json(422, validation_message(exc.errors()), errors=errors)


async def _http(_: Request, exc: StarletteHTTPException) -> JSONResponse:
    if exc.status_code == 204 or exc.status_code == 304:
        return JSONResponse(None, status_code=exc.status_code, headers=exc.headers)
    return JSONResponse({"detail": str(exc.detail)}, status_code=exc.status_code, headers=exc.headers)


async def _store_unavailable(request: Request, exc: StoreUnavailable) -> JSONResponse:
    # The database's address stays in the server log, not in the answer.
    log.warning("job database unavailable on %s %s: %s", request.method, request.url.path, exc)
    return JSONResponse({"detail": "the job database is unavailable; retry in a moment"}, status_code=503,
                        headers={"Retry-After": "5"})


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return _json(500, f"internal server error ({exc.__class__.__name__}); the server log has the details")


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(RequestValidationError, _validation)
    app.add_exception_handler(StarletteHTTPException, _http)
    app.add_exception_handler(JobNotFound, lambda _r, e: _json(404, str(e)))
    app.add_exception_handler(JobConflict, lambda _r, e: _json(409, str(e)))
    app.add_exception_handler(BundleError, lambda _r, e: _json(422, str(e)))
    app.add_exception_handler(LambdaMapError, lambda _r, e: _json(422, str(e)))
    app.add_exception_handler(UploadTooLarge, lambda _r, e: _json(413, str(e)))
    app.add_exception_handler(StoreUnavailable, _store_unavailable)
    app.add_exception_handler(Exception, _unexpected)


JSON_BODY_BYTES = 1024 * 1024  # a job spec or a λ edit (rects) is a few KiB
# A λ map is one channel at the job's image size: at most 2048² float32 pixels plus headers;
# an uncompressed EXR or 16-bit PNG of it is 16 MiB.
MAP_UPLOAD_BYTES = 32 * 1024 * 1024


def _mib(n: int) -> str:
    return f"{n / 2**20:g} MiB"


class BodySizeLimit:
    """Pure ASGI middleware: refuse bodies over the route's cap, by header or while streaming.
    Only a bundle upload (multipart POST /jobs) gets `max_bytes`; a λ map upload gets
    MAP_UPLOAD_BYTES; every other body (JSON) JSON_BODY_BYTES, so no route reads a
    gigabyte of JSON."""

    def __init__(self, app: ASGIApp, max_bytes: int, json_bytes: int = JSON_BODY_BYTES,
                 map_bytes: int = MAP_UPLOAD_BYTES) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.json_bytes = json_bytes
        self.map_bytes = map_bytes

    def limit_for(self, scope: Scope) -> tuple[int, str]:
        """(cap, what it is for) for this request."""
        headers = dict(scope.get("headers", []))
        multipart = headers.get(b"content-type", b"").lower().startswith(b"multipart/form-data")
        method, path = scope["method"], scope["path"].rstrip("/")
        if multipart and method == "POST" and path == "/jobs":
            return self.max_bytes, "scene upload"
        if multipart and method == "PUT" and path.startswith("/jobs/") and path.endswith("/lambda"):
            return self.map_bytes, "λ map upload"
        return self.json_bytes, "request body"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit, what = self.limit_for(scope)
        declared = dict(scope.get("headers", [])).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            response = _json(413, f"{what} of {int(declared)} bytes exceeds the {_mib(limit)} cap")
            await response(scope, receive, send)
            return
        seen = 0

        async def counted() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise UploadTooLarge(f"{what} exceeds the {_mib(limit)} cap")
            return message

        await self.app(scope, counted, send)
