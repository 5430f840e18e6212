"""The two backends are two implementations of one protocol (service/jobs/runner.py), not a
class and its subclass: each has every JobRunner method with the protocol's parameters, and
neither inherits from the other."""
from __future__ import annotations

import inspect

import pytest

from service.jobs.ray_worker import RayJobWorker  # Ray is required: no skip
from service.jobs.runner import JobRunner
from service.jobs.worker import JobWorker

BACKENDS = [JobWorker, RayJobWorker]
PROTOCOL_METHODS = [name for name, member in vars(JobRunner).items()
                    if inspect.isfunction(member) and not name.startswith("_")]


def test_the_protocol_names_what_the_api_calls():
    assert {"start", "stop", "submit", "cancel", "delete", "files", "image_size", "current_lambda", "set_lambda",
            "health_problem"} <= set(PROTOCOL_METHODS)


@pytest.mark.parametrize("backend", BACKENDS, ids=lambda cls: cls.__name__)
def test_each_backend_implements_every_method_of_the_job_runner_protocol(backend):
    for name in PROTOCOL_METHODS:
        expected = list(inspect.signature(getattr(JobRunner, name)).parameters)
        assert list(inspect.signature(getattr(backend, name)).parameters) == expected, name


def test_neither_backend_subclasses_the_other():
    thread_backend, ray_backend = BACKENDS
    assert not issubclass(ray_backend, thread_backend) and not issubclass(thread_backend, ray_backend)
