"""How a server runs its jobs (service.jobs.backends builds the worker from this); kept free of
heavy imports so the command line can parse `serve` options without loading torch or Ray."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class WorkerSettings:
    """`concurrency` set: the thread backend with that many threads. Otherwise Ray: `workers`
    jobs at once on a local runtime this server starts (None: one per core), or the cluster at
    `ray_address` (refused without Ray's token auth unless `insecure_ray`)."""

    concurrency: int | None = None
    workers: int | None = None
    ray_address: str | None = None
    insecure_ray: bool = False

    def __post_init__(self) -> None:
        if self.concurrency is not None and (self.workers is not None or self.ray_address):
            raise ValueError("choose the thread backend (concurrency) or Ray (workers, ray address), not both")
        for name in ("concurrency", "workers"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"{name} must be >= 1")

    @property
    def uses_ray(self) -> bool:
        return self.concurrency is None

    def describe(self) -> str:
        if not self.uses_ray:
            return f"{self.concurrency} render thread(s) in this process"
        if self.ray_address:
            return f"Ray cluster at {self.ray_address}"
        return f"local Ray runtime, {self.workers or 'one per core'} worker(s)"


THREADS = WorkerSettings(concurrency=1)  # today's in-process behaviour, one job at a time
