"""A job's preview layers and their publication: every set of frames goes out under one new
version (the store's counter, bumped under a per-job lock so concurrent publishers — an
iteration's writer and a λ edit — never interleave their files).

An iteration's previews are written where they are published (already off the render path, on
the checkpoint's thread). A λ edit's are published in memory and written by `writes` (a
LatestWriter) after the request was answered: `load` serves the newest version from memory
until its files landed, and a write older than what is already on disk is skipped."""
from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from service.jobs.artifacts import JobFiles, Preview
from service.jobs.latest_writer import LatestWriter
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


@dataclass(frozen=True)
class Unwritten:
    """A published version whose files are still to be written."""

    version: int
    frames: list[dict[str, np.ndarray | None]]


class PreviewPublisher:
    """Writes all frames' previews of a job under one new version."""

    def __init__(self, store) -> None:
        self.store = store
        self.writes = LatestWriter("job-writes")   # a λ edit's previews and results, off its request
        self._lock = threading.Lock()
        self._locks: dict[str, threading.Lock] = {}
        self._unwritten: dict[str, Unwritten] = {}

    def publish(self, job_id: str, files: JobFiles, frames: list[dict[str, np.ndarray | None]]) -> int:
        """Returns the version the frames went out under (written before this returns)."""
        with self._job_lock(job_id):
            version = self.store.bump_preview_version(job_id)
            for f, layers in enumerate(frames):
                files.save_preview(f, Preview(version=version, layers=layers))
            with self._lock:
                unwritten = self._unwritten.get(job_id)
                if unwritten is not None and unwritten.version < version:
                    del self._unwritten[job_id]   # older than these files: never to be written
            return version

    def publish_later(self, job_id: str, files: JobFiles, frames: list[dict[str, np.ndarray | None]]) -> int:
        """The version the frames go out under: `load` returns them at once, their files are
        written in the background."""
        with self._lock:   # not the job's file lock: a write in flight must not hold up the answer
            version = self.store.bump_preview_version(job_id)
            self._unwritten[job_id] = Unwritten(version, frames)
        self.writes.submit(job_id, "previews", lambda: self._write_unwritten(job_id, files, version))
        return version

    def load(self, job_id: str, files: JobFiles, frame: int) -> Preview | None:
        """The newest published preview of `frame`: from memory while its files are unwritten."""
        with self._lock:
            unwritten = self._unwritten.get(job_id)
        if unwritten is not None and frame < len(unwritten.frames):
            return Preview(version=unwritten.version, layers=dict(unwritten.frames[frame]))
        return files.load_preview(frame)

    def forget(self, job_id: str) -> None:
        self.writes.discard(job_id)
        with self._lock:
            self._locks.pop(job_id, None)
            self._unwritten.pop(job_id, None)

    def _write_unwritten(self, job_id: str, files: JobFiles, version: int) -> None:
        """On the writer's thread: the files of `version`, unless a newer version took its place."""
        with self._job_lock(job_id):
            with self._lock:
                unwritten = self._unwritten.get(job_id)
            if unwritten is None or unwritten.version != version:
                return
            for f, layers in enumerate(unwritten.frames):
                files.save_preview(f, Preview(version=version, layers=layers))
            with self._lock:
                if self._unwritten.get(job_id) is unwritten:
                    del self._unwritten[job_id]

    def _job_lock(self, job_id: str) -> threading.Lock:
        with self._lock:
            return self._locks.setdefault(job_id, threading.Lock())
