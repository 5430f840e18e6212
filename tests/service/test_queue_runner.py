"""The queue's threads with a real store: two threads can pick the same queued job, and only
the one that claims it runs it and tells its backend when it ended (the other must not clear
the winner's cancel flag or live entry: seen as a Ray job that ran on after its cancel)."""
from __future__ import annotations

import threading
import time

from service.jobs.queue_runner import QueueRunner
from service.loop.spec import LoopSpec
from worker_jobs import store  # noqa: F401  (a fixture)

WAIT_SECONDS = 60.0


def test_the_thread_that_lost_the_claim_does_not_end_the_job_the_other_runs(store):
    spec = LoopSpec(scene="cornell-box", width=16, height=16)
    job_id = store.create(spec.to_stored(), spec.lam).id
    both_took_it = threading.Barrier(2, timeout=WAIT_SECONDS)  # both picked the queued job before a claim
    lost_claim, release = threading.Event(), threading.Event()
    ended: list[str] = []

    def run(job: str) -> bool:
        both_took_it.wait()
        if not store.claim(job):
            lost_claim.set()
            return False
        release.wait(WAIT_SECONDS)  # the winner is still running its job
        return True

    stopping = threading.Event()
    queue = QueueRunner(store, 2, run=run, ended=ended.append, live=lambda: (), stopping=stopping)
    try:
        queue.kick()
        assert lost_claim.wait(WAIT_SECONDS)
        deadline = time.monotonic() + 2.0  # the loser's thread ends its turn within this
        while time.monotonic() < deadline and not ended:
            time.sleep(0.02)
        assert ended == [], "the thread that lost the claim ended the job the other one runs"
        release.set()
        deadline = time.monotonic() + WAIT_SECONDS
        while time.monotonic() < deadline and not ended:
            time.sleep(0.02)
        assert ended == [job_id]
    finally:
        release.set()
        stopping.set()
        queue.stop()
