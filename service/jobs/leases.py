"""Job leases: which server runs a job, and until when that claim holds.

A server that claims a job writes itself as `lease_owner` and a `lease_expires_at` a lease
length ahead, and renews it every `renew_seconds` while the job runs (service/jobs/worker.py).
Every server sweeps every `sweep_seconds`: a running job whose lease lapsed lost its server
(kill -9, a dead node), so it goes back to the queue and whoever claims it resumes from the
checkpoint in the shared data dir. A server starting up requeues only jobs whose lease lapsed
or whose owner was a process on this host that is gone — never a live other server's job.

The owner names host, process and a per-store nonce (`host/pid/nonce`), so two servers on one
host (or two stores in one process) never mistake each other's leases for their own.
"""
from __future__ import annotations

import os
import socket
import uuid
from dataclasses import dataclass

LEASE_SECONDS_ENV = "RENDERLOOP_LEASE_SECONDS"
DEFAULT_LEASE_SECONDS = 30.0  # a lapse is noticed within 30 s + one sweep; renewals every 10 s
MIN_LEASE_SECONDS = 0.5


@dataclass(frozen=True)
class Leases:
    seconds: float = DEFAULT_LEASE_SECONDS

    def __post_init__(self) -> None:
        if not self.seconds >= MIN_LEASE_SECONDS:
            raise ValueError(f"a lease must last at least {MIN_LEASE_SECONDS} s, got {self.seconds}")

    @property
    def renew_seconds(self) -> float:
        # Three renewals per lease: one late or failed renewal (a busy database) does not lose it.
        return self.seconds / 3

    @property
    def sweep_seconds(self) -> float:
        return self.seconds / 3

    @classmethod
    def from_env(cls) -> "Leases":
        value = os.environ.get(LEASE_SECONDS_ENV)
        return cls(float(value)) if value else cls()


def new_owner() -> str:
    """This store's name in `lease_owner`: host/pid/nonce."""
    return f"{socket.gethostname()}/{os.getpid()}/{uuid.uuid4().hex[:8]}"


def owner_is_gone(owner: str | None) -> bool:
    """True when `owner` was a process on this host that no longer exists (a server killed and
    restarted here); False when it may be alive or lives elsewhere — its lease then decides."""
    if not owner:
        return False
    parts = owner.split("/")
    if len(parts) != 3 or parts[0] != socket.gethostname() or not parts[1].isdigit():
        return False
    pid = int(parts[1])
    if pid == os.getpid():
        return False  # this very process: another store in it, alive
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False  # someone else's process holds that pid now: leave it to the lease
    return False
