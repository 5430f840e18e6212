"""One job's checkpoint (`DATA/jobs/<id>/state/`): the one owner of reading, writing and
copying it, and of knowing which iteration is on disk.

Both backends write it the same way, off the render path: after an iteration the state is
copied (LoopState.snapshot, into the previous write's arrays: ~1/10 of a save at 2 MP, see
service/jobs/checkpoint_writer.py) and saved on a background thread while the next iteration
renders; what must follow the save (the thread worker's previews and record) runs on that
thread right after it. `through` is the last iteration on disk, and `wait_through(n)` blocks
until iteration n is there, so whoever records an iteration (the thread worker's writer, the
Ray driver asking the leader actor) never records one a restart could not resume from.

The format (the npz files, the atomic directory swap) is service/jobs/checkpoint_format.py's.
"""
from __future__ import annotations

import threading
from pathlib import Path
from typing import Callable

from service.jobs import checkpoint_format
from service.jobs.checkpoint_writer import CheckpointWriter
from service.loop.state import LoopState


class CheckpointFailed(RuntimeError):
    """A background save failed; raised with the save's own exception as its cause."""


class JobCheckpoint:
    """The checkpoint of one job; background saves start a thread on first use."""

    def __init__(self, directory: Path, name: str = "job") -> None:
        self.directory = Path(directory)
        self._name = name
        self._writer: CheckpointWriter | None = None
        self._spare: LoopState | None = None  # the last write's snapshot, free once it landed
        self._done = threading.Condition()
        self._through = -1  # unknown until read or written: exists()/load() set it
        self._failure: BaseException | None = None

    # -- reading --------------------------------------------------------------------------------

    def exists(self) -> bool:
        return checkpoint_format.holds_state(self.directory)

    def load(self) -> LoopState | None:
        """The state on disk, or None when the job has no checkpoint yet."""
        if not self.exists():
            return None
        state = checkpoint_format.read_state(self.directory)
        self._landed(state.iteration)
        return state

    @property
    def through(self) -> int:
        """The last iteration known to be on disk (0: none)."""
        with self._done:
            return max(self._through, 0)

    # -- writing --------------------------------------------------------------------------------

    def snapshot(self, state: LoopState) -> LoopState:
        """A copy of `state` for `write_in_background`, made after the previous write landed
        (one copy in memory at a time, into that write's arrays). A failed earlier write is
        raised here, on the caller's thread."""
        self._background().wait()
        self._spare = state.snapshot(reuse=self._spare)
        return self._spare

    def write_in_background(self, snapshot: LoopState,
                            then: Callable[[LoopState], None] = lambda snapshot: None) -> None:
        """Save `snapshot` (from `snapshot()`) on the background thread, then run
        `then(snapshot)` there; the caller goes on rendering."""
        self._background().submit(lambda: self._write(snapshot, then))

    def wait(self) -> float:
        """Wait for the write in flight; re-raise what it raised. Returns the seconds waited."""
        return self._writer.wait() if self._writer is not None else 0.0

    def wait_through(self, iteration: int, timeout: float | None = None) -> None:
        """Block until iteration `iteration` is on disk; raise CheckpointFailed if its save
        failed, TimeoutError after `timeout` seconds."""
        with self._done:
            landed = self._done.wait_for(lambda: self._through >= iteration or self._failure is not None, timeout)
            if self._through >= iteration:
                return
            if not landed:
                raise TimeoutError(f"checkpoint of iteration {iteration} not written within {timeout} s")
            raise CheckpointFailed(f"{self._failure.__class__.__name__}: {self._failure}") from self._failure

    def close(self) -> None:
        """The job ends: a write still running lands (its error is logged, not raised: the job
        ends with an error of its own); the thread ends."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def _background(self) -> CheckpointWriter:
        if self._writer is None:
            self._writer = CheckpointWriter(self._name)
        return self._writer

    def _write(self, snapshot: LoopState, then: Callable[[LoopState], None]) -> None:
        try:
            checkpoint_format.write_state(snapshot, self.directory)
        except BaseException as exc:
            with self._done:
                self._failure = exc
                self._done.notify_all()
            raise
        self._landed(snapshot.iteration)
        then(snapshot)

    def _landed(self, iteration: int) -> None:
        with self._done:
            self._through = max(self._through, iteration)
            self._done.notify_all()
