"""How the server ends on SIGTERM (what systemd, docker and Kubernetes send): uvicorn stops
accepting, cuts open event streams after the grace, runs the app's shutdown (running jobs stop
within one wavefront chunk and are requeued, a local Ray runtime is shut down) — and then
re-raises the signal so the process dies *by* it (status 143 / -15). A stop that was asked for
and done cleanly is status 0 here, the exit supervisors read as success."""
from __future__ import annotations

import signal
from contextlib import contextmanager
from types import FrameType
from typing import Iterator


def _exit_0(signum: int, frame: FrameType | None) -> None:
    # Only reached outside uvicorn's own handler: before it runs (nothing started yet: just
    # leave) or when it re-raises the signal after its graceful shutdown (all done: leave).
    raise SystemExit(0)


@contextmanager
def sigterm_exits_0() -> Iterator[None]:
    """Run the server inside this: a SIGTERM ends the process with status 0 once uvicorn's
    graceful shutdown is through. uvicorn keeps the handler it finds and restores it after."""
    previous = signal.signal(signal.SIGTERM, _exit_0)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
