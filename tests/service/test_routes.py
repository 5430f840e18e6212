"""The routes' helpers alone, without a server: job lookup, the frame-range check, λ from JSON."""
from __future__ import annotations

import pytest
from fastapi.exceptions import RequestValidationError

from service.api.routes import check_frame, require_job
from service.jobs.errors import JobNotFound
from service.jobs.store import JobState, JobStore
from service.loop.spec import LoopSpec


@pytest.fixture
def store(tmp_path) -> JobStore:
    return JobStore(tmp_path)


def test_require_job_names_the_missing_id(store):
    with pytest.raises(JobNotFound, match="nope"):
        require_job(store, "nope")


def test_a_new_job_is_queued_and_its_spec_parses_back(store):
    spec = LoopSpec(scene="cornell-box", width=8, height=8, frames=3)
    record = require_job(store, store.create(spec.to_stored(), spec.lam).id)
    assert record.state == JobState.QUEUED and LoopSpec.from_stored(record.spec) == spec


def test_check_frame_accepts_every_frame_of_the_job_and_refuses_the_next(store):
    spec = LoopSpec(scene="cornell-box", width=8, height=8, frames=3)
    record = store.create(spec.to_stored(), spec.lam)
    for frame in range(3):
        check_frame(record, frame)
    with pytest.raises(RequestValidationError) as caught:
        check_frame(record, 3)
    assert "frame 3 out of range: the job has 3" in str(caught.value.errors())
