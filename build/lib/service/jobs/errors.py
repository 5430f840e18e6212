"""Job-level failures the HTTP layer turns into status codes (404, 409)."""
from __future__ import annotations


class JobNotFound(LookupError):
    """No job with that id (404)."""


class JobConflict(RuntimeError):
    """The request makes no sense in the job's current state (409); the message says why."""
