"""GET /jobs/{id}/links: URLs of a job's preview and event stream that need no header, for
browser elements that cannot send one (`<img>`, `EventSource`). On a server with a token they
carry a short-lived signature (service.api.signing) instead of the token."""
from __future__ import annotations

from urllib.parse import quote, urlencode

from pydantic import BaseModel, Field
from starlette.requests import Request

from service.api.signing import UrlSigner

SIGNER_STATE = "url_signer"  # request.state key; service.api.security.RequestGuard sets it


class JobLinks(BaseModel):
    events: str = Field(description="GET: the job's server-sent events")
    preview: str = Field(description="GET: the job's preview; add frame, layer, format, exposure as usual")
    expires: int | None = Field(description="unix seconds after which both stop working; null: they need no "
                                            "signature (the server has no token)")


def request_signer(request: Request) -> UrlSigner | None:
    return getattr(request.state, SIGNER_STATE, None)


def job_links(job_id: str, signer: UrlSigner | None) -> JobLinks:
    base = f"/jobs/{quote(job_id, safe='')}"
    if signer is None:
        return JobLinks(events=f"{base}/events", preview=f"{base}/preview", expires=None)
    expires, signature = signer.sign(job_id)
    query = urlencode({"exp": expires, "sig": signature})
    return JobLinks(events=f"{base}/events?{query}", preview=f"{base}/preview?{query}", expires=expires)
