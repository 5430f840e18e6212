"""The artist's web page: `GET /` serves index.html, `/page/…` its CSS and JavaScript modules
(service/api/page/, shipped as package data; no build step). Served without a token so the
page can load and ask for one (service.api.security.OPEN_PATHS); everything it shows comes
from the guarded API."""
from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.responses import FileResponse
from starlette.responses import Response
from starlette.staticfiles import StaticFiles
from starlette.types import Scope

PAGE_DIR = Path(__file__).with_name("page")
PAGE_PREFIX = "/page"
# Only our own scripts, styles and API; blob: for the brush's and the download's object URLs.
# No framing: a page that is clickable under someone else's frame could be made to cancel jobs.
CONTENT_SECURITY_POLICY = ("default-src 'self'; img-src 'self' blob: data:; script-src 'self'; style-src 'self'; "
                           "connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'none'; "
                           "frame-ancestors 'none'")
PAGE_HEADERS = {"Content-Security-Policy": CONTENT_SECURITY_POLICY, "X-Content-Type-Options": "nosniff",
                "Cache-Control": "no-cache"}

router = APIRouter(include_in_schema=False)


@router.get("/")
def index() -> FileResponse:
    return FileResponse(PAGE_DIR / "index.html", media_type="text/html; charset=utf-8", headers=PAGE_HEADERS)


class PageFiles(StaticFiles):
    """The page's static files with the same headers as the page (revalidated on every load,
    so an upgraded server never runs yesterday's script against today's API)."""

    async def get_response(self, path: str, scope: Scope) -> Response:
        response = await super().get_response(path, scope)
        response.headers.update(PAGE_HEADERS)
        return response


def install_page(app: FastAPI) -> None:
    app.include_router(router)
    app.mount(PAGE_PREFIX, PageFiles(directory=PAGE_DIR), name="page")
