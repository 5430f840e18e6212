"""A job's record (one row of the jobs table, decoded) and what the workers and routes read
from it: its state, and its stored spec as the loop's LoopSpec (`job_spec`, `bundle_scene`).
The store (service/jobs/store.py) writes records; everything else reads them through here."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from service.loop.spec import LoopSpec


class JobState(StrEnum):
    """A job's life: queued → running → one of the three terminal states (stored as text)."""

    QUEUED = "queued"
    RUNNING = "running"
    COMPLETED = "completed"
    FAILED = "failed"
    CANCELED = "canceled"


QUEUED, RUNNING, COMPLETED, FAILED, CANCELED = JobState
STATES = tuple(state.value for state in JobState)
TERMINAL_STATES = frozenset({COMPLETED, FAILED, CANCELED})
CANCELED_WHILE_QUEUED = "canceled before it started"


@dataclass
class JobRecord:
    """One row of the jobs table, decoded."""

    id: str
    state: str
    spec: dict[str, Any]
    iteration: int = 0  # finished iterations
    spp: float = 0.0  # mean samples per pixel so far
    predicted_error: float | None = None
    stop_reason: str | None = None
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage, summed
    error: str | None = None
    created_at: float = 0.0  # unix seconds
    started_at: float | None = None
    finished_at: float | None = None
    preview_version: int = 0
    lambda_value: float | None = None  # the global λ last set; None once a per-pixel map is set
    resumed_from: int | None = None  # iteration the last restart resumed at; None if never resumed
    effects: dict[str, Any] | None = None  # the effects report once the scene is loaded
    priority: int = 0  # higher-priority queued jobs are claimed first
    client: str | None = None  # who submitted it (service.jobs.quotas.client_key)
    idempotency_key: str | None = None
    lease_owner: str | None = None  # the server that runs (or last ran) it
    lease_expires_at: float | None = None
    eta_seconds: float | None = None  # seconds left as estimated after the last iteration (loop/eta.py)
    eta_finish_at: float | None = None  # unix seconds: when that estimate ends the job
    eta_basis: str | None = None  # what the estimate rests on, in words
    stop_message: str | None = None  # stop_reason in words (loop/stop_message.py)

    @property
    def finished(self) -> bool:
        return self.state in TERMINAL_STATES

    @classmethod
    def from_row(cls, row: dict[str, Any]) -> "JobRecord":
        values = dict(row)
        values["spec"] = json.loads(values["spec"])
        values["timings"] = json.loads(values["timings"])
        values["effects"] = json.loads(values["effects"]) if values.get("effects") else None
        return cls(**values)


def job_spec(record: JobRecord, bundle_dir: Path | None = None) -> LoopSpec:
    """A job record's stored spec as the loop's LoopSpec; a bundle's scene resolves inside
    `bundle_dir` (left relative without it)."""
    values = {key: value for key, value in record.spec.items() if key != "bundle_scene"}
    entry = bundle_scene(record)
    scene = str(bundle_dir / entry) if (entry and bundle_dir is not None) else None
    return LoopSpec.from_stored(values, scene=scene)


def bundle_scene(record: JobRecord) -> str | None:
    """The entry XML of an uploaded job, relative to its bundle; None for a built-in scene."""
    return record.spec["bundle_scene"] if "bundle_scene" in record.spec else None
