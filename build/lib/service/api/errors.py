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
from service.jobs.errors import JobConflict, JobNotFound

log = logging.getLogger(__name__)


class UploadTooLarge(ValueError):
    """The request body is over the upload cap (413)."""


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
    app.add_exception_handler(Exception, _unexpected)


class BodySizeLimit:
    """Pure ASGI middleware: refuse bodies over `max_bytes`, by header or while streaming."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.max_bytes
        declared = dict(scope.get("headers", [])).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            response = _json(413, f"request body of {int(declared)} bytes exceeds the {limit // (1024 * 1024)} MiB cap")
            await response(scope, receive, send)
            return
        seen = 0

        async def counted() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise UploadTooLarge(f"request body exceeds the {limit // (1024 * 1024)} MiB cap")
            return message

        await self.app(scope, counted, send)
