"""λ edits of a job, whichever backend runs it: the saved map, a per-job latest-wins mailbox
(under a burst only the newest request is applied, and every caller gets the version that
shows it), the re-denoise (the backend's `relambda`: wherever the job's loop lives) and the
preview it publishes.

What an edit waits for before its answer: the λ map on disk (the durable record of the edit: a
crash right after the answer still leaves it for the resumed job; 8 MB at 2 MP) and the new image
in memory, published as the next preview version. What it does not wait for: writing the preview
layers and a finished job's result EXRs (about a second at 2 MP, measured: docs/models-speed.md),
done by the publisher's LatestWriter; a GET of the preview reads the memory until then, a GET of
the result and a graceful stop flush them (`flush`). A process killed between the answer and
those writes leaves a finished job's files one edit behind its saved map; the first read of its
preview or result in the next process notices (the files' λ layer is not the saved map) and
applies the saved map again (`_catch_up`)."""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from service.exr import ExrFrame, read_exr
from service.jobs.artifacts import JobFiles, Preview
from service.jobs.errors import JobConflict, JobNotFound
from service.jobs.latest import LatestWins
from service.jobs.previews import PreviewPublisher
from service.jobs.record import CANCELED, COMPLETED, FAILED, JobRecord, job_spec

LAMBDA_WAIT_SECONDS = 300.0

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LambdaApplied:
    """What one λ application did: the preview version showing it, and the denoiser work it
    took (full forward passes vs. λ-only tail passes from cached features)."""

    version: int
    full_passes: int = 0
    tail_passes: int = 0
    # Seconds of each part of the edit (`_apply`'s parts and the backend's, Relambda.timings;
    # "edit": from the request to this version, a wait behind a newer request included): what
    # the API reports in its Server-Timing header (bench/lambda_edit.py splits the round trip by it).
    timings: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Relambda:
    """A λ re-denoise: the new image per frame, the denoiser work it took, and how to build the
    result frames from it (None where the loop lives elsewhere and keeps them itself). `results`
    is called on the writer's thread, after the answer, without the loop's lock (building them at
    2 MP takes longer than the tail and would hold the next edit up): an edit replaces the λ map
    and the images, never writes into them, and every edit's own write follows its re-denoise,
    so the file the last write leaves is the last edit's."""

    images: list[np.ndarray]
    full_passes: int = 0
    tail_passes: int = 0
    results: Callable[[], list[ExrFrame]] | None = None
    # seconds: "denoise" (the loop's re-denoise where it lives: the λ tail and the final image),
    # "tail" (the λ tail within it), "hop" (Ray: the actor calls' round trip beyond "denoise",
    # the maps through the object store)
    timings: dict[str, float] = field(default_factory=dict)


# The backend's re-denoise of a job with a λ map: None when nothing was rendered yet.
Relambdas = Callable[[str, JobRecord, np.ndarray], "Relambda | None"]


def require(store, job_id: str) -> JobRecord:
    """The job's record, or JobNotFound (404)."""
    record = store.get(job_id)
    if record is None:
        raise JobNotFound(f"no job with id {job_id!r}")
    return record


class LambdaEdits:
    def __init__(self, store, previews: PreviewPublisher, relambda: Relambdas,
                 observed: Callable[[float], None],
                 flush_elsewhere: Callable[[str | None], None] = lambda job_id: None) -> None:
        self.store = store
        self.previews = previews
        self._relambda = relambda
        self._flush_elsewhere = flush_elsewhere  # writes the backend makes away from here (a Ray worker's)
        self._observed = observed  # seconds from a request to the version that shows it
        self._lock = threading.Lock()
        self._mailboxes: dict[str, LatestWins[tuple[np.ndarray, float | None], LambdaApplied]] = {}
        self._caught_up: set[str] = set()  # finished jobs whose files this process checked or wrote

    def files(self, job_id: str) -> JobFiles:
        return JobFiles(self.store.job_dir(job_id))

    def image_size(self, job_id: str) -> tuple[int, int] | None:
        """(H, W) of the job's images, once known (spec, or the first preview)."""
        spec = job_spec(require(self.store, job_id))
        if spec.width and spec.height:
            return spec.height, spec.width
        preview = self.load_preview(job_id, 0)
        if preview is not None and preview.layers.get("noisy") is not None:
            return preview.layers["noisy"].shape[:2]
        return None

    def load_preview(self, job_id: str, frame: int) -> Preview | None:
        """The newest preview of `frame`, a λ edit's included before its files are written."""
        self._catch_up(job_id)
        return self.previews.load(job_id, self.files(job_id), frame)

    def flush(self, job_id: str | None = None) -> None:
        """Wait until the job's (every job's, with None) edits are on disk: previews and results."""
        self.previews.writes.flush(job_id)
        self._flush_elsewhere(job_id)

    def result_path(self, job_id: str, frame: int) -> Path:
        """The frame's result EXR, with the job's last λ edit written into it."""
        self._catch_up(job_id)
        self.flush(job_id)
        return self.files(job_id).result_path(frame)

    def current_lambda(self, job_id: str, shape: tuple[int, int]) -> np.ndarray:
        record = require(self.store, job_id)
        lam = self.files(job_id).load_lambda()
        if lam is not None and lam.shape == shape:
            return lam
        return np.full(shape, job_spec(record).lam, dtype=np.float32)

    def set_lambda(self, job_id: str, lam: np.ndarray, value: float | None = None,
                   sequence: int | None = None) -> LambdaApplied:
        """Keep `lam` with the job and re-denoise from cached features. Under a burst only the
        newest request is applied (newest by the client's `sequence` when it sends one, else
        by arrival); every caller gets the version that shows it."""
        started = time.perf_counter()
        record = require(self.store, job_id)
        if record.state in (FAILED, CANCELED):
            raise JobConflict(f"job {job_id} is {record.state}: there is nothing left to re-denoise")
        mailbox = self._mailbox(job_id)
        applied = mailbox.wait(mailbox.submit((lam, value), order=sequence), timeout=LAMBDA_WAIT_SECONDS)
        seconds = time.perf_counter() - started
        self._observed(seconds)
        return LambdaApplied(applied.version, applied.full_passes, applied.tail_passes, {**applied.timings, "edit": seconds})

    def _catch_up(self, job_id: str) -> None:
        """Once per process and finished job: if its files were written for another λ than the
        saved map (the process that answered the edit died before writing them), apply the saved
        map again, so the preview and the result show the edit that was answered with a 200."""
        with self._lock:
            if job_id in self._caught_up:
                return
            self._caught_up.add(job_id)
        record = self.store.get(job_id)
        files = self.files(job_id)
        lam = files.load_lambda()
        if record is None or record.state != COMPLETED or lam is None or _files_show(files, lam):
            return
        log.info("job %s: its preview and result were written before its last λ edit (the process that "
                 "answered it stopped first); applying the saved λ map again", job_id)
        self.set_lambda(job_id, lam, record.lambda_value)
        self.flush(job_id)

    def _mailbox(self, job_id: str) -> LatestWins[tuple[np.ndarray, float | None], LambdaApplied]:
        with self._lock:
            if job_id not in self._mailboxes:
                self._mailboxes[job_id] = LatestWins(
                    lambda request: self._apply(job_id, *request), name=f"lambda-{job_id[:8]}"
                )
            return self._mailboxes[job_id]

    def _apply(self, job_id: str, lam: np.ndarray, value: float | None) -> LambdaApplied:
        # Persisted here, before the answer and on the one thread that applies this job's λ, so
        # the saved map is always the newest request's; later iterations and restarts read it
        # (a loop that opens reads it after registering: one this edit missed still sees it).
        started = time.perf_counter()
        files = self.files(job_id)
        files.save_lambda(lam)
        with self._lock:
            self._caught_up.add(job_id)  # this process writes the files that follow: nothing to catch up
        self.store.set_lambda_value(job_id, value)
        record = require(self.store, job_id)
        saved = time.perf_counter()
        done = self._relambda(job_id, record, lam)
        denoised = time.perf_counter()
        timings = {"save": saved - started, "relambda": denoised - saved, **(done.timings if done else {})}
        if done is None:
            return LambdaApplied(record.preview_version, timings=timings)  # nothing rendered yet: used from iteration 1
        if not done.images:
            return LambdaApplied(record.preview_version, done.full_passes, done.tail_passes, timings)
        frames = []
        for f, image in enumerate(done.images):
            previous = self.previews.load(job_id, files, f)
            layers = dict(previous.layers) if previous else {"noisy": None, "error": None, "spp": None}
            frames.append({**layers, "denoised": image, "lambda": lam})
        version = self.previews.publish_later(job_id, files, frames)
        if done.results is not None and require(self.store, job_id).state == COMPLETED:
            build = done.results   # the result follows λ after the run too
            self.previews.writes.submit(job_id, "results", lambda: files.save_results(build()))
        timings["publish"] = time.perf_counter() - denoised
        return LambdaApplied(version, done.full_passes, done.tail_passes, timings)


def _files_show(files: JobFiles, lam: np.ndarray) -> bool:
    """Whether frame 0's preview and result (those that exist) were written with λ map `lam`."""
    preview = files.load_preview(0)
    if preview is not None and preview.layers.get("lambda") is not None \
            and not np.array_equal(preview.layers["lambda"], lam):
        return False
    result = files.result_path(0)
    return not result.is_file() or np.array_equal(read_exr(result).lam, lam)


class LambdaEditsOfRunner:
    """The λ part of the JobRunner protocol, the same on both backends: what differs (where a
    job's loop lives and re-denoises) is the `relambda` their LambdaEdits was built with."""

    lambdas: LambdaEdits

    def image_size(self, job_id: str) -> tuple[int, int] | None:
        return self.lambdas.image_size(job_id)

    def current_lambda(self, job_id: str, shape: tuple[int, int]) -> np.ndarray:
        return self.lambdas.current_lambda(job_id, shape)

    def load_preview(self, job_id: str, frame: int) -> Preview | None:
        return self.lambdas.load_preview(job_id, frame)

    def result_path(self, job_id: str, frame: int) -> Path:
        return self.lambdas.result_path(job_id, frame)

    def set_lambda(self, job_id: str, lam: np.ndarray, value: float | None = None,
                   sequence: int | None = None) -> LambdaApplied:
        """Keep `lam` with the job and re-denoise it from cached features (wherever its loop lives)."""
        return self.lambdas.set_lambda(job_id, lam, value, sequence)

