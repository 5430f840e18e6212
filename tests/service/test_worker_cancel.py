"""When a cancel comes too late to matter: the worker with a real store, real renders and the
cancel delivered at an exact point (right after an iteration is published), so the outcome does
not depend on timing."""
from __future__ import annotations

import pytest

from service.jobs.store import CANCELED, COMPLETED
from service.jobs.worker import JobWorker
from worker_jobs import run_tiny_job, store  # noqa: F401  (store: a fixture)


class CancelAfterEachIteration(JobWorker):
    """A worker whose user presses cancel the moment each iteration is checkpointed and
    published: for the last iteration, that is after all the job's work is done."""

    def _finish_iteration(self, job_id, loop, files, record, timings):
        timings = super()._finish_iteration(job_id, loop, files, record, timings)
        self.cancel(job_id)
        return timings


@pytest.mark.parametrize("iterations, state, stop_reason", [
    (1, COMPLETED, "max_iterations"),  # the cancel came after the last iteration: too late to matter
    (3, CANCELED, "canceled"),  # after the first of three: the job stops there
])
def test_a_cancel_after_an_iteration_cancels_only_a_job_with_iterations_left(store, tiny_networks, iterations,
                                                                               state, stop_reason):
    worker = CancelAfterEachIteration(store, tiny_networks)
    try:
        done = run_tiny_job(store, worker, iterations=iterations)
    finally:
        worker.stop()
    assert (done.state, done.stop_reason, done.iteration) == (state, stop_reason, 1)
    assert worker.files(done.id).result_path(0).is_file()  # what was rendered is kept either way
