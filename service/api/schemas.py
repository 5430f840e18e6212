"""Request and response bodies of the HTTP API, with the limits a job may ask for."""
from __future__ import annotations

from datetime import datetime, timezone
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from service.jobs.store import JobRecord

MAX_SIDE = 4096
MAX_PIXELS = 2048 * 2048  # per frame
MAX_FRAMES = 16
MAX_ITERATIONS = 12
MAX_SPP_FIRST = 1024
MAX_TOTAL_SAMPLES = 2**33  # pixels × frames × mean spp over the whole job
MAX_TIME_LIMIT = 7 * 24 * 3600.0
LAMBDA_MIN, LAMBDA_MAX = 1.0, 10.0
MAX_RECTS = 1024
# A JSON body may only name a built-in scene: no dots or slashes, so never a server path.
BUILTIN_SCENE_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_\-]*$"
BUNDLE_SCENE_PATTERN = r"^[^\x00]+\.[xX][mM][lL]$"  # checked for escapes by service.jobs.bundle

Allocator = Literal["error", "variance", "uniform"]
Layer = Literal["denoised", "noisy", "error", "spp", "lambda"]
ImageFormat = Literal["png", "exr"]


class JobCreate(BaseModel):
    """POST /jobs as JSON: `scene` names a built-in scene."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    scene: str = Field(min_length=1, max_length=128, pattern=BUILTIN_SCENE_PATTERN)
    width: int | None = Field(None, ge=1, le=MAX_SIDE, description="None: the scene's own film size")
    height: int | None = Field(None, ge=1, le=MAX_SIDE)
    frames: int = Field(1, ge=1, le=MAX_FRAMES)
    spp_first: int = Field(16, ge=1, le=MAX_SPP_FIRST)
    max_iterations: int | None = Field(4, ge=1, le=MAX_ITERATIONS)
    spp_budget: float | None = Field(None, gt=0, description="mean samples per pixel, all iterations")
    time_limit: float | None = Field(None, gt=0, le=MAX_TIME_LIMIT, description="seconds")
    target_error: float | None = Field(None, gt=0, description="stop at this mean predicted SMAPE")
    allocator: Allocator = "error"
    denoise: bool = True
    lam: float = Field(1.0, alias="lambda", ge=LAMBDA_MIN, le=LAMBDA_MAX)
    seed: int = Field(0, ge=0, le=2**31 - 1)

    @model_validator(mode="after")
    def _check_together(self) -> "JobCreate":
        if (self.width is None) != (self.height is None):
            raise ValueError("give both width and height, or neither (the scene's own size)")
        if self.width is not None and self.width * self.height > MAX_PIXELS:
            raise ValueError(f"width × height = {self.width * self.height} exceeds the cap of {MAX_PIXELS} pixels")
        if self.max_iterations is None and self.spp_budget is None:
            # Every iteration doubles the samples: without one of these the job never ends cheaply.
            raise ValueError("give max_iterations or spp_budget to bound the total samples")
        if not self.denoise and self.allocator == "error" and self.max_iterations != 1:
            raise ValueError("allocator 'error' needs the denoiser; use 'variance' or 'uniform' with denoise=false")
        if self.width is not None and self.planned_samples() > MAX_TOTAL_SAMPLES:
            raise ValueError(f"the job would take {self.planned_samples():.3g} samples, over the cap of {MAX_TOTAL_SAMPLES:.3g}")
        return self

    def planned_mean_spp(self) -> float:
        """Upper bound on the final mean spp: the first pass doubled each later iteration."""
        by_iterations = self.spp_first * 2.0 ** (self.max_iterations - 1) if self.max_iterations else float("inf")
        return min(by_iterations, self.spp_budget or float("inf"))

    def planned_samples(self) -> float:
        return (self.width or 0) * (self.height or 0) * self.frames * self.planned_mean_spp()

    def stored_spec(self, bundle_scene: str | None = None) -> dict:
        """The spec as kept in the job record (`lambda` under its public name)."""
        spec = self.model_dump(by_alias=True)
        spec["bundle_scene"] = bundle_scene
        return spec


class BundleJobCreate(JobCreate):
    """The `spec` field of a multipart bundle upload: `scene` is the XML inside the bundle
    (optional when the bundle has exactly one top-level XML)."""

    scene: str | None = Field(None, min_length=1, max_length=512, pattern=BUNDLE_SCENE_PATTERN)


class JobCreated(BaseModel):
    id: str
    state: str


def _iso(timestamp: float | None) -> str | None:
    return None if timestamp is None else datetime.fromtimestamp(timestamp, timezone.utc).isoformat()


class JobStatus(BaseModel):
    id: str
    state: str
    iteration: int
    spp: float
    predicted_error: float | None
    stop_reason: str | None
    timings: dict[str, float]
    error: str | None
    created_at: str | None
    started_at: str | None
    finished_at: str | None
    preview_version: int
    lambda_value: float | None = Field(None, description="global λ last set; null once a per-pixel map is used")
    resumed_from: int | None = Field(None, description="iteration a restart resumed this job at")
    spec: dict

    @classmethod
    def from_record(cls, record: JobRecord) -> "JobStatus":
        return cls(
            id=record.id,
            state=record.state,
            iteration=record.iteration,
            spp=record.spp,
            predicted_error=record.predicted_error,
            stop_reason=record.stop_reason,
            timings=record.timings,
            error=record.error,
            created_at=_iso(record.created_at),
            started_at=_iso(record.started_at),
            finished_at=_iso(record.finished_at),
            preview_version=record.preview_version,
            lambda_value=record.lambda_value,
            resumed_from=record.resumed_from,
            spec=record.spec,
        )


class JobList(BaseModel):
    jobs: list[JobStatus]


class LambdaRect(BaseModel):
    model_config = ConfigDict(extra="forbid")

    x: int = Field(ge=0)
    y: int = Field(ge=0)
    w: int = Field(ge=1)
    h: int = Field(ge=1)
    value: float = Field(ge=LAMBDA_MIN, le=LAMBDA_MAX)


class LambdaUpdate(BaseModel):
    """PUT /jobs/{id}/lambda as JSON: a global λ, or rectangles painted over the current map."""

    model_config = ConfigDict(extra="forbid")

    value: float | None = Field(None, ge=LAMBDA_MIN, le=LAMBDA_MAX)
    rects: list[LambdaRect] | None = Field(None, min_length=1, max_length=MAX_RECTS)

    @model_validator(mode="after")
    def _exactly_one(self) -> "LambdaUpdate":
        if (self.value is None) == (self.rects is None):
            raise ValueError("give exactly one of 'value' or 'rects'")
        return self


class LambdaResult(BaseModel):
    version: int = Field(description="preview version that shows the newest λ")
    full_passes: int = Field(0, description="full denoiser passes this took (a rebuild after a restart)")
    tail_passes: int = Field(0, description="λ-only passes from cached features")


class Health(BaseModel):
    status: str
    jobs: dict[str, int]
