"""GET /info: what renders this server's jobs — CPU or GPU, which Mitsuba variant, which
backend — so the page (and a pipeline) can say what a job will run on before submitting it."""
from __future__ import annotations

from pydantic import BaseModel, Field

from service.render.runtime import choose_variant

GPU_VARIANT_PREFIX = "cuda_"
GPU_VARIANT = "cuda_ad_rgb"


class ServerInfo(BaseModel):
    device: str = Field(description="'GPU' or 'CPU': where the jobs render")
    variant: str = Field(description="the Mitsuba variant jobs render with")
    backend: str = Field(description="'threads' (in the server process) or 'ray' (worker processes)")
    summary: str = Field(description="the above in words")


def server_info(worker: object) -> ServerInfo:
    """The render device of `worker`'s jobs: the Ray backend's actors ask for a GPU when the
    cluster has one (service/jobs/ray_worker.py) and then pick the CUDA variant themselves;
    the thread backend renders here, with this process's variant."""
    ray_gpus = getattr(worker, "_gpus", None)  # set only by the Ray backend
    backend = "threads" if ray_gpus is None else "ray"
    variant = choose_variant()
    if ray_gpus and not variant.startswith(GPU_VARIANT_PREFIX):
        variant = GPU_VARIANT
    device = "GPU" if variant.startswith(GPU_VARIANT_PREFIX) else "CPU"
    where = "in the server process" if backend == "threads" else "in Ray worker processes"
    return ServerInfo(device=device, variant=variant, backend=backend,
                      summary=f"renders on the {device} (Mitsuba {variant}), {where}")
