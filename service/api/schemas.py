"""Request and response bodies of the HTTP API, with the limits a job may ask for."""
from __future__ import annotations

import dataclasses
import re
from datetime import datetime, timezone
from typing import Annotated, Any, Literal, get_type_hints

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, create_model, model_validator

from service.jobs.store import JobRecord
from service.loop.spec import (ALLOCATORS, LAMBDA_RANGE, MAX_NAME_CHARS, MAX_SEED, PRIORITY_RANGE, SERVICE_LIMITS,
                               LoopSpec, LoopSpecError, job_name, lambda_problem, validate_spec)

MAX_RECTS = 1024
MAX_SEQUENCE = 2**63 - 1
SEQUENCE_DESCRIPTION = ("optional: when the edit was issued, in milliseconds since the Unix epoch (one job's "
                        "editors must share this clock); an edit that arrives after one with a higher number is "
                        "dropped, so edits that overtake each other on the way still end on the newest")
# A JSON body may only name a built-in scene: no dots or slashes, so never a server path.
BUILTIN_SCENE_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_\-]*$"
BUNDLE_SCENE_PATTERN = r"^[^\x00]+\.[xX][mM][lL]$"  # checked for escapes by service.jobs.bundle

Allocator = Literal[ALLOCATORS]  # type: ignore[valid-type]
Layer = Literal["denoised", "noisy", "error", "spp", "lambda"]
ImageFormat = Literal["png", "exr"]
LAMBDA_MIN, LAMBDA_MAX = LAMBDA_RANGE

# Field bounds the schema states (and OpenAPI documents); all come from loop/spec.py.
_BOUNDS: dict[str, dict[str, Any]] = {
    "width": {"ge": 1, "le": SERVICE_LIMITS.max_side, "description": "null: the scene's own film size"},
    "height": {"ge": 1, "le": SERVICE_LIMITS.max_side},
    "frames": {"ge": 1, "le": SERVICE_LIMITS.max_frames},
    "spp_first": {"ge": 1, "le": SERVICE_LIMITS.max_spp_first},
    "max_iterations": {"ge": 1, "le": SERVICE_LIMITS.max_iterations},
    "spp_budget": {"gt": 0, "description": "mean samples per pixel, all iterations"},
    "time_limit": {"gt": 0, "le": SERVICE_LIMITS.max_time_limit, "description": "seconds"},
    "target_error": {"gt": 0, "description": "stop at this mean predicted SMAPE"},
    # The range is documented here but checked by validate_spec, so every way in gives the same message.
    "lam": {"alias": "lambda", "json_schema_extra": {"minimum": LAMBDA_MIN, "maximum": LAMBDA_MAX}},
    "seed": {"ge": 0, "le": MAX_SEED},
    "params": {"description": "the scene's $name parameters, like Mitsuba's -D name=value"},
    "allocator": {"description": "null: 'error' with the denoiser, 'variance' without"},
    "priority": {"ge": PRIORITY_RANGE[0], "le": PRIORITY_RANGE[1],
                 "description": "queue order: higher-priority queued jobs start first"},
    "name": {"min_length": 1, "max_length": MAX_NAME_CHARS,
             "description": "what listings call the job; null: the bundle's entry XML, or the built-in scene's name"},
}
# Strict: "32" is not a width and "yes" not a boolean; NaN and ±Infinity are no numbers here.
_STRICT = ConfigDict(extra="forbid", populate_by_name=True, strict=True, allow_inf_nan=False)


def _spec_fields() -> dict[str, tuple[Any, Any]]:
    """Every LoopSpec field but `scene`, with its type, default and bounds."""
    hints = get_type_hints(LoopSpec)
    hints["allocator"] = Allocator | None
    out = {}
    for f in dataclasses.fields(LoopSpec):
        if f.name in ("scene", "budget_source"):  # budget_source is set by the server, never asked for
            continue
        default = f.default if f.default is not dataclasses.MISSING else None
        factory = f.default_factory if f.default_factory is not dataclasses.MISSING else None
        bounds = _BOUNDS.get(f.name, {})
        info = Field(default_factory=factory, **bounds) if factory else Field(default, **bounds)
        out[f.name] = (hints[f.name], info)
    return out


class _SpecBody(BaseModel):
    model_config = _STRICT

    def loop_spec(self, scene: str) -> LoopSpec:
        values = self.model_dump(exclude={"scene"})
        return LoopSpec(scene=scene, **values)

    @model_validator(mode="after")
    def _check_spec(self):
        # The same rules as every other way in (CLI, worker): loop/spec.py's validate_spec.
        try:
            validate_spec(self.loop_spec(getattr(self, "scene", None) or "bundle"))
        except LoopSpecError as exc:
            raise ValueError(str(exc)) from exc
        return self


def builtin_scene_name(value: str) -> str:
    """A JSON body names a built-in scene; a file name there means the user wanted an upload,
    so say how to make one instead of quoting the pattern."""
    if not re.match(BUILTIN_SCENE_PATTERN, value):
        raise ValueError(f"{value!r} is not a built-in scene name (GET /scenes lists them). To render your own scene "
                         "file, upload it: multipart POST /jobs with spec={\"scene\": \"scene.xml\"} and the zipped "
                         "folder as bundle")
    return value


JobCreate = create_model(
    "JobCreate", __base__=_SpecBody, __doc__="POST /jobs as JSON: `scene` names a built-in scene.",
    # The pattern is documented in the schema and checked by builtin_scene_name (a clearer message).
    scene=(Annotated[str, AfterValidator(builtin_scene_name)],
           Field(min_length=1, max_length=128, json_schema_extra={"pattern": BUILTIN_SCENE_PATTERN})),
    **_spec_fields(),
)
BundleJobCreate = create_model(
    "BundleJobCreate", __base__=_SpecBody,
    __doc__="The `spec` field of a multipart bundle upload: `scene` is the XML inside the bundle "
            "(optional when the bundle has exactly one top-level XML).",
    scene=(str | None, Field(None, min_length=1, max_length=512, pattern=BUNDLE_SCENE_PATTERN)), **_spec_fields(),
)


class ErrorBody(BaseModel):
    """Every refusal: what is wrong, in one message (422s also list the fields)."""

    detail: str
    errors: list[dict] | None = None


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
    effects: dict | None = Field(None, description="the effects report: which integrator runs and why, what is simulated")
    priority: int = Field(0, description="queue order: higher-priority queued jobs start first")
    name: str = Field("", description="the job's name: given at submit, else the bundle's or the scene's name")
    eta_seconds: float | None = Field(None, description="seconds left as estimated after the last iteration (each "
                                      "doubles the samples); 0 once completed, null when unknown or not running")
    eta_finish_at: str | None = Field(None, description="when that estimate says the job ends")
    eta_basis: str | None = Field(None, description="what the estimate rests on, in words")
    stop_message: str | None = Field(None, description="stop_reason in words: which rule ended the job, what was left unused")
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
            effects=record.effects,
            priority=record.priority,
            name=record_name(record),
            spec=record.spec,
            **eta_fields(record),
            stop_message=record.stop_message,
        )


def eta_fields(record: JobRecord) -> dict[str, Any]:
    """The ETA while the job runs (0 once it completed); none for a queued, failed or canceled job."""
    if record.state == "completed":
        return {"eta_seconds": 0.0, "eta_basis": "finished"}
    if record.state != "running":
        return {}
    return {"eta_seconds": record.eta_seconds, "eta_finish_at": _iso(record.eta_finish_at), "eta_basis": record.eta_basis}


def record_name(record: JobRecord) -> str:
    """The stored name; records from before names were stored get the one they would have had."""
    spec = record.spec
    return spec.get("name") or job_name(LoopSpec(scene=str(spec.get("scene", ""))), spec.get("bundle_scene"))


class JobList(BaseModel):
    jobs: list[JobStatus]


def _lambda_value(value: float | None) -> float | None:
    # loop/spec.py's check, so a λ out of range reads the same here as in the loop and the CLI.
    problem = None if value is None else lambda_problem(value)
    if problem:
        raise ValueError(problem)
    return value


LambdaValue = Annotated[float, AfterValidator(_lambda_value),
                        Field(json_schema_extra={"minimum": LAMBDA_MIN, "maximum": LAMBDA_MAX})]


class LambdaRect(BaseModel):
    model_config = _STRICT

    x: int = Field(ge=0)
    y: int = Field(ge=0)
    w: int = Field(ge=1)
    h: int = Field(ge=1)
    value: LambdaValue


class LambdaUpdate(BaseModel):
    """PUT /jobs/{id}/lambda as JSON: a global λ, or rectangles painted over the current map."""

    model_config = _STRICT

    value: LambdaValue | None = None
    rects: list[LambdaRect] | None = Field(None, min_length=1, max_length=MAX_RECTS)
    sequence: int | None = Field(None, ge=0, le=MAX_SEQUENCE, description=SEQUENCE_DESCRIPTION)

    @model_validator(mode="after")
    def _exactly_one(self) -> "LambdaUpdate":
        if (self.value is None) == (self.rects is None):
            raise ValueError("give exactly one of 'value' or 'rects'")
        return self


class LambdaResult(BaseModel):
    version: int = Field(description="preview version that shows the newest λ")
    full_passes: int = Field(0, description="full denoiser passes this took (a rebuild after a restart)")
    tail_passes: int = Field(0, description="λ-only passes from cached features")


class SceneInfo(BaseModel):
    name: str
    description: str
    width: int
    height: int
    effects: dict = Field(description="the effects report: which integrator runs and why, what is simulated")


class SceneList(BaseModel):
    scenes: list[SceneInfo]


class Health(BaseModel):
    status: str  # "ok", or "unavailable" (503) when no job can run
    jobs: dict[str, int]
    message: str | None = None  # why it is unavailable
