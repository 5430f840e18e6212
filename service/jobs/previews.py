"""A job's preview layers and their publication: every set of frames goes out under one new
version (the store's counter, bumped under a per-job lock so concurrent publishers — an
iteration's writer and a λ edit — never interleave their files)."""
from __future__ import annotations

import threading

import numpy as np

from service.jobs.artifacts import JobFiles, Preview
from service.loop.loop import RenderLoop
from service.loop.spec import IterationRecord
from service.loop.state import LoopState


def preview_layers(loop: RenderLoop, record: IterationRecord) -> list[dict[str, np.ndarray | None]]:
    """Each frame's preview layers after an iteration (JobFiles.save_preview takes them)."""
    return state_preview_layers(loop.state, record)


def state_preview_layers(state: LoopState, record: IterationRecord) -> list[dict[str, np.ndarray | None]]:
    """The preview layers of `record` with the λ map of `state` (a snapshot's, when written in
    the background)."""
    lam = state.lam_map
    return [
        {
            "denoised": record.denoised[f] if record.denoised else buf.raw,
            "noisy": buf.raw,
            "error": record.error[f] if f < len(record.error) else None,
            "spp": buf.spp.astype(np.float32),
            "lambda": lam,
        }
        for f, buf in enumerate(record.buffers)
    ]


class PreviewPublisher:
    """Writes all frames' previews of a job under one new version."""

    def __init__(self, store) -> None:
        self.store = store
        self._lock = threading.Lock()
        self._locks: dict[str, threading.Lock] = {}

    def publish(self, job_id: str, files: JobFiles, frames: list[dict[str, np.ndarray | None]]) -> int:
        """Returns the version the frames went out under."""
        with self._job_lock(job_id):
            version = self.store.bump_preview_version(job_id)
            for f, layers in enumerate(frames):
                files.save_preview(f, Preview(version=version, layers=layers))
            return version

    def forget(self, job_id: str) -> None:
        with self._lock:
            self._locks.pop(job_id, None)

    def _job_lock(self, job_id: str) -> threading.Lock:
        with self._lock:
            return self._locks.setdefault(job_id, threading.Lock())
