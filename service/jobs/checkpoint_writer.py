"""A job's checkpoint and preview writes, off the render path.

After each iteration the worker hands a snapshot of the loop state (copies of the arrays the
next iteration mutates) to this writer and goes on rendering; one background thread saves the
checkpoint, publishes the previews and records the iteration, in that order, while the loop
renders the next iteration. At most one write is in flight: `submit` first waits for the one
before (memory stays bounded to one extra copy of the state, writes keep their order), and a
write that failed is re-raised on the job's thread by the next `submit` or by `flush`, so a
failed write still fails the job.

What the render path still pays is the snapshot (LoopState.snapshot). Measured on the shared
2-core host (load ~3), one frame with every buffer and the splat sums (396 MiB of float64 at
1920×1080, 200 MiB at 1024²), median of 5: at 2 MP a save (checkpoint_format.write_state)
504 ms (235–1182), a fresh snapshot 84 ms (but 0.6–1.1 s while the allocator still faults
its pages in), a snapshot into the previous one's arrays 46 ms (22–60); at 1024² save
334 ms, snapshot 81 ms, reused 35 ms. So the job's checkpoint (service/jobs/checkpoints.py)
reuses the last write's snapshot, and the render path pays ~1/10 of the write. The Ray driver
uses one of these too, for the previews and the record that follow the leader actor's checkpoint.
"""
from __future__ import annotations

import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

log = logging.getLogger("service.jobs.worker")  # one logger for the worker's messages


class CheckpointWriter:
    """One background thread for one job's writes; queue depth 1."""

    def __init__(self, name: str) -> None:
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"checkpoint-{name}")
        self._pending: Future | None = None

    def wait(self) -> float:
        """Wait for the write in flight, if any; re-raise what it raised. Returns seconds waited."""
        started = time.perf_counter()
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()  # re-raises the write's exception here, on the job's thread
        return time.perf_counter() - started

    def submit(self, write: Callable[[], None]) -> None:
        """Start `write` in the background; the previous write must have finished (call `wait`
        first to measure it; otherwise it is waited for here)."""
        self.wait()
        try:
            self._pending = self._executor.submit(write)
        except RuntimeError:
            # The interpreter is exiting (concurrent.futures refuses new work once the main
            # thread is gone: a SIGTERM'd server whose render thread finishes its iteration
            # after the app shut down). Write here, on the job's thread, so the checkpoint the
            # requeued job resumes from is complete; a failed write still fails the job.
            write()

    def flush(self) -> None:
        """The job ends (complete, cancel, requeue, lease lost): its last write lands first."""
        self.wait()

    def close(self) -> None:
        """Let a write still running finish, without raising (the job already ends with an error
        of its own), then end the thread."""
        try:
            self.wait()
        except Exception:  # noqa: BLE001 — the job's own error is the one reported
            log.exception("a checkpoint write failed while its job was ending with an error of its own")
        finally:
            self._executor.shutdown(wait=True)
