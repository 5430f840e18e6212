"""A job's preview layers and their publication: every set of frames goes out under one new
version (the store's counter, bumped under a per-job lock so concurrent publishers — an
iteration's writer and a λ edit — never interleave their files).

An iteration's previews are written where they are published (already off the render path, on
the checkpoint's thread). A λ edit's are published in memory and written by `writes` (a
LatestWriter) after the request was answered: `load` serves the newest version from memory
(kept for the last EDITED_JOBS_KEPT edited jobs, written or not), and a write older than what is
already on disk is skipped."""
from __future__ import annotations

import threading
from collections import OrderedDict
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


# λ edits keep their published frames in memory for this many jobs, the newest edited last,
# once their files are written too: the next edit carries the noisy/error/spp layers over from
# there instead of reading the preview file again (~40 MB at 2 MP), and GETs read no file.
EDITED_JOBS_KEPT = 2


@dataclass(frozen=True)
class Published:
    """A λ edit's frames under one version, `written` once their files landed."""

    version: int
    frames: list[dict[str, np.ndarray | None]]
    written: bool = False


class PreviewPublisher:
    """Writes all frames' previews of a job under one new version."""

    def __init__(self, store) -> None:
        self.store = store
        self.writes = LatestWriter("job-writes")   # a λ edit's previews and results, off its request
        self._lock = threading.Lock()
        self._locks: dict[str, threading.Lock] = {}
        self._edited: OrderedDict[str, Published] = OrderedDict()   # λ edits' frames, newest job last

    def publish(self, job_id: str, files: JobFiles, frames: list[dict[str, np.ndarray | None]]) -> int:
        """Returns the version the frames went out under (written before this returns). Not kept
        in memory: an iteration's layers are the checkpoint snapshot's arrays, which the next
        snapshot reuses."""
        with self._job_lock(job_id):
            version = self.store.bump_preview_version(job_id)
            for f, layers in enumerate(frames):
                files.save_preview(f, Preview(version=version, layers=layers))
            with self._lock:
                edited = self._edited.get(job_id)
                if edited is not None and edited.version < version:
                    del self._edited[job_id]   # older than these files (and never to be written)
            return version

    def publish_later(self, job_id: str, files: JobFiles, frames: list[dict[str, np.ndarray | None]]) -> int:
        """The version a λ edit's frames go out under: `load` returns them at once, their files
        are written in the background. The arrays must not change afterwards."""
        with self._lock:   # not the job's file lock: a write in flight must not hold up the answer
            version = self.store.bump_preview_version(job_id)
            self._edited[job_id] = Published(version, frames)
            self._edited.move_to_end(job_id)
            self._forget_written_beyond_kept()
        self.writes.submit(job_id, "previews", lambda: self._write_edited(job_id, files, version))
        return version

    def load(self, job_id: str, files: JobFiles, frame: int) -> Preview | None:
        """The newest published preview of `frame`: a λ edit's from memory, else the file."""
        with self._lock:
            edited = self._edited.get(job_id)
        if edited is not None and frame < len(edited.frames):
            return Preview(version=edited.version, layers=dict(edited.frames[frame]))
        return files.load_preview(frame)

    def forget(self, job_id: str) -> None:
        self.writes.discard(job_id)
        with self._lock:
            self._locks.pop(job_id, None)
            self._edited.pop(job_id, None)

    def _write_edited(self, job_id: str, files: JobFiles, version: int) -> None:
        """On the writer's thread: the files of `version`, unless a newer version took its place."""
        with self._job_lock(job_id):
            with self._lock:
                edited = self._edited.get(job_id)
            if edited is None or edited.version != version:
                return
            for f, layers in enumerate(edited.frames):
                files.save_preview(f, Preview(version=version, layers=layers))
            with self._lock:
                if self._edited.get(job_id) is edited:
                    self._edited[job_id] = Published(version, edited.frames, written=True)
                    self._forget_written_beyond_kept()

    def _forget_written_beyond_kept(self) -> None:
        """Under the lock: the oldest written entries beyond EDITED_JOBS_KEPT go (an unwritten one
        stays until its files land: it is the only copy of that version)."""
        written = [job for job, edited in self._edited.items() if edited.written]
        for job in written[:max(0, len(self._edited) - EDITED_JOBS_KEPT)]:
            del self._edited[job]

    def _job_lock(self, job_id: str) -> threading.Lock:
        with self._lock:
            return self._locks.setdefault(job_id, threading.Lock())
