"""Admission control on submit: how many jobs may wait in the queue, for the whole store and for
one client (its bearer token, else its address), and whether the data folder has room for one
more bundle (serve --max-queued, --max-queued-per-client, --max-disk-gb). A refusal says when to
come back (429 + Retry-After) or that the disk is full (507); nothing grows without bound."""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass

MAX_QUEUED_ENV = "RENDERLOOP_MAX_QUEUED"
MAX_QUEUED_PER_CLIENT_ENV = "RENDERLOOP_MAX_QUEUED_PER_CLIENT"
DEFAULT_MAX_QUEUED = 100
DEFAULT_MAX_QUEUED_PER_CLIENT = 20
# A queued job leaves the queue when a worker is free, typically after tens of seconds: a
# client told to retry sooner would only be refused again.
RETRY_AFTER_SECONDS = 30
MAX_IDEMPOTENCY_KEY = 255


@dataclass(frozen=True)
class Quotas:
    max_queued: int = DEFAULT_MAX_QUEUED  # queued jobs in the store, all clients together
    max_queued_per_client: int = DEFAULT_MAX_QUEUED_PER_CLIENT
    retry_after_seconds: int = RETRY_AFTER_SECONDS

    def __post_init__(self) -> None:
        if self.max_queued < 1 or self.max_queued_per_client < 1:
            raise ValueError("queue caps must be >= 1")

    @classmethod
    def from_env(cls) -> "Quotas":
        total, per_client = os.environ.get(MAX_QUEUED_ENV), os.environ.get(MAX_QUEUED_PER_CLIENT_ENV)
        return cls(max_queued=int(total) if total else DEFAULT_MAX_QUEUED,
                   max_queued_per_client=int(per_client) if per_client else DEFAULT_MAX_QUEUED_PER_CLIENT)


class QuotaExceeded(RuntimeError):
    """The queue is full, for everyone or for this client (429); retry after `retry_after` s."""

    def __init__(self, message: str, retry_after: int) -> None:
        super().__init__(message)
        self.retry_after = retry_after


class DiskFull(RuntimeError):
    """The data folder is at its cap even after removing finished jobs (507)."""


def client_key(token: str | None, address: str | None) -> str:
    """Who a submit counts against: a digest of its bearer token (the token itself never lands
    in the database), else the address it came from."""
    if token:
        return "token:" + hashlib.sha256(token.encode()).hexdigest()[:32]
    return f"addr:{address or 'unknown'}"


def check_idempotency_key(value: str) -> str:
    """Printable ASCII, bounded: it is stored and compared, never interpreted."""
    if not 1 <= len(value) <= MAX_IDEMPOTENCY_KEY or not value.isascii() or not value.isprintable():
        raise ValueError(f"Idempotency-Key must be 1 to {MAX_IDEMPOTENCY_KEY} printable ASCII characters")
    return value
