"""Short-lived signed URLs for the two routes a browser element fetches without headers
(`<img>` previews, `EventSource` event streams), so the bearer token never rides in a query
string, where access logs, browser history and Referer headers would keep it.

A URL carries `?exp=<unix seconds>&sig=<HMAC-SHA256 over the job id and exp>`; it grants the
job's preview and events, read-only, until `exp`. The key is derived from the server's token,
not the token itself: a leaked URL opens one job for minutes and never yields the token;
servers sharing a token (one PostgreSQL store) accept each other's URLs; changing the token
revokes every URL issued under the old one."""
from __future__ import annotations

import base64
import hashlib
import hmac
import time
from dataclasses import dataclass

SIGNED_URL_SECONDS = 300
SIGNED_SUFFIXES = ("/events", "/preview")
JOBS_PREFIX = "/jobs/"
KEY_CONTEXT = b"renderloop signed job urls v1"


def signed_job_id(path: str) -> str | None:
    """`/jobs/ID/events` or `/jobs/ID/preview` → ID; None for any other path."""
    for suffix in SIGNED_SUFFIXES:
        if path.startswith(JOBS_PREFIX) and path.endswith(suffix):
            job_id = path[len(JOBS_PREFIX):-len(suffix)]
            if job_id and "/" not in job_id:
                return job_id
    return None


@dataclass(frozen=True)
class UrlSigner:
    key: bytes
    seconds: int = SIGNED_URL_SECONDS

    @classmethod
    def from_token(cls, token: str, seconds: int = SIGNED_URL_SECONDS) -> "UrlSigner":
        return cls(hmac.new(token.encode(), KEY_CONTEXT, hashlib.sha256).digest(), seconds)

    def sign(self, job_id: str, now: float | None = None) -> tuple[int, str]:
        """(exp, sig) for this job, valid for `seconds` from now."""
        expires = int(time.time() if now is None else now) + self.seconds
        return expires, self._mac(job_id, expires)

    def verify(self, job_id: str, expires: str, signature: str, now: float | None = None) -> bool:
        if not expires.isdigit() or len(expires) > 12:
            return False
        if int(expires) < (time.time() if now is None else now):
            return False
        return hmac.compare_digest(self._mac(job_id, int(expires)).encode(), signature.encode())

    def _mac(self, job_id: str, expires: int) -> str:
        digest = hmac.new(self.key, f"{job_id}\n{expires}".encode(), hashlib.sha256).digest()
        return base64.urlsafe_b64encode(digest).rstrip(b"=").decode()
