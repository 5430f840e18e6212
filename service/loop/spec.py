"""THE job spec: what a render job asks for, its defaults, its validation and the limits a
service puts on it. The API schema (service/api/schemas.py), the CLI defaults and the worker
all derive from this file; the stored job spec is parsed back into `LoopSpec` here.

Also what each loop iteration hands back (IterationRecord).
"""
from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

from models.lambda_range import LAMBDA_MAX, LAMBDA_MIN
from service.render.framebuffer import FrameBuffer

ALLOCATORS = ("error", "variance", "uniform")
STOP_REASONS = ("max_iterations", "spp_budget", "time_limit", "target_error", "canceled")
# The λ range the denoiser was trained for (eq. 6; log λ ~ U(0, log 10)): one source of truth.
LAMBDA_RANGE = (LAMBDA_MIN, LAMBDA_MAX)
DEFAULT_ITERATIONS = 4  # when no stopping rule is given: 16 → 128 spp with the default first pass
DEFAULT_SPP_FIRST = 16  # Vogels et al. 2018 §7: the first iteration renders 16 spp uniformly
MAX_SEED = 2**31 - 1
# Scene parameters are Mitsuba's `-D name=value`: identifiers, short values.
PARAM_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")
MAX_PARAMS, MAX_PARAM_VALUE = 64, 1024
# A service job's place in the queue: higher runs first; the loop itself ignores it.
PRIORITY_RANGE = (-100, 100)
# A job's name, shown in listings (`renderloop jobs`, GET /jobs, the page): one printable line.
MAX_NAME_CHARS = 128


class LoopSpecError(ValueError):
    """A job asks for something the loop cannot do (or a service will not); the message says what."""


@dataclass(frozen=True)
class JobLimits:
    """Caps a service puts on one job, checked on the effective job (the film size read from
    the scene when the request gives none). Local CLI renders are not capped."""

    max_side: int = 4096
    max_pixels: int = 2048 * 2048  # per frame
    max_frames: int = 16
    max_iterations: int = 12
    max_spp_first: int = 1024
    max_total_samples: float = 2.0**33  # pixels × frames × final mean spp
    max_time_limit: float = 7 * 24 * 3600.0
    max_memory_bytes: float = 8 * 2.0**30  # estimated_memory of the job (serve --max-job-memory-gb)


SERVICE_LIMITS = JobLimits()
# What a job holds in memory: a fixed part (Python, Mitsuba, torch and one 2^22-lane wavefront
# chunk: `renderloop bench --memory` measured 0.73 GB for a whole 1024² pass) plus, per pixel and
# frame, the float64 sums of the per-pixel and the splatted estimates, the background checkpoint's
# copy of them (service/jobs/checkpoints.py), the denoiser's cached features over the pyramid, the
# error map, the final image's raw share and temporaries. Measured as the peak RSS growth of a
# cornell-box RenderLoop, 2 iterations with a state snapshot each, shipped networks, 2 threads:
# 0.59 GiB at 512², 2.07 GiB at 1024², 3.81 GiB at 1920×1080 — about 2 000 B per pixel
# (tests/loop/test_job_memory.py re-measures at 1024²). 2 304 B leaves ~15 % headroom.
BASE_JOB_BYTES = 0.6e9
BYTES_PER_PIXEL_FRAME = 2304


def estimated_memory(width: int, height: int, frames: int) -> float:
    """Bytes a job needs while it runs (see BASE_JOB_BYTES, BYTES_PER_PIXEL_FRAME)."""
    return BASE_JOB_BYTES + BYTES_PER_PIXEL_FRAME * width * height * frames


def default_allocator(denoise: object) -> str:
    """The error allocator predicts the *denoised* error, so a job without the denoiser
    steers by variance instead."""
    return "error" if denoise is not False else "variance"


@dataclass
class LoopSpec:
    """A render job. `scene` is a built-in scene name or a path to a Mitsuba XML file."""

    scene: str
    width: int | None = None  # None (with height None): the scene's own film size
    height: int | None = None
    frames: int = 1
    spp_first: int = DEFAULT_SPP_FIRST  # iteration 0, uniform
    max_iterations: int | None = DEFAULT_ITERATIONS
    spp_budget: float | None = None  # mean samples per pixel, all iterations together
    time_limit: float | None = None  # seconds of loop wall time
    target_error: float | None = None  # stop once mean predicted SMAPE <= this
    allocator: str | None = None  # None: "error" with the denoiser, "variance" without (it needs none)
    denoise: bool = True
    lam: float = 1.0  # default λ (1 = symmetric loss)
    seed: int = 0
    params: dict[str, str] = field(default_factory=dict)  # the scene's `$name` parameters (Mitsuba's -D)
    # "scene": spp_budget is the scene's own <sampler> sample_count, set because the job gave no
    # stopping rule (service/loop/budget.py); None: the budget is the request's (or the default).
    budget_source: str | None = None
    priority: int = 0  # queue order on a service (PRIORITY_RANGE); no effect on the image
    name: str | None = None  # what listings call the job; None: the service names it (see job_name)

    def __post_init__(self) -> None:
        if self.allocator is None:
            self.allocator = default_allocator(self.denoise)

    def to_stored(self) -> dict[str, Any]:
        """The spec as kept in a job record (JSON; `lambda` under its public name)."""
        stored = asdict(self)
        stored["lambda"] = stored.pop("lam")
        return stored

    @classmethod
    def from_stored(cls, stored: dict[str, Any], *, scene: str | None = None) -> "LoopSpec":
        """Parse a stored spec back (unknown keys are an error, not silently dropped)."""
        values = dict(stored)
        if "lambda" in values:
            values["lam"] = values.pop("lambda")
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise LoopSpecError(f"unknown job spec field(s): {', '.join(sorted(unknown))}")
        if scene is not None:
            values["scene"] = scene
        return cls(**values)

    def planned_mean_spp(self) -> float:
        """Upper bound on the final mean spp: the first pass, doubled by each later iteration."""
        by_iterations = self.spp_first * 2.0 ** (self.max_iterations - 1) if self.max_iterations else math.inf
        return min(by_iterations, self.spp_budget if self.spp_budget is not None else math.inf)


def _is_int(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def lambda_problem(values: np.ndarray | float) -> str | None:
    """Why these λ values are unusable (non-finite or outside LAMBDA_RANGE), or None."""
    array = np.asarray(values, dtype=np.float64)
    low, high = LAMBDA_RANGE
    if array.size and (not np.isfinite(array).all() or array.min() < low or array.max() > high):
        return f"λ must be finite and lie in [{low:g}, {high:g}]"
    return None


def validate_spec(spec: LoopSpec) -> None:
    """Types, ranges and the stopping rule; raises LoopSpecError naming the first problem."""
    for name in ("width", "height"):
        value = getattr(spec, name)
        if value is not None and (not _is_int(value) or value < 1):
            raise LoopSpecError(f"{name} must be an integer >= 1, got {value!r}")
    if (spec.width is None) != (spec.height is None):
        raise LoopSpecError("give both width and height, or neither (the scene's own size)")
    for name in ("frames", "spp_first"):
        value = getattr(spec, name)
        if not _is_int(value) or value < 1:
            raise LoopSpecError(f"{name} must be an integer >= 1, got {value!r}")
    if spec.max_iterations is not None and (not _is_int(spec.max_iterations) or spec.max_iterations < 1):
        raise LoopSpecError(f"max_iterations must be an integer >= 1, got {spec.max_iterations!r}")
    for name in ("spp_budget", "time_limit", "target_error"):
        value = getattr(spec, name)
        if value is not None and (not _is_number(value) or not math.isfinite(value) or not value > 0):
            raise LoopSpecError(f"{name} must be a finite number > 0, got {value!r}")
    if spec.spp_budget is not None and _is_number(spec.spp_budget) and spec.spp_budget < spec.spp_first:
        # the first iteration renders spp_first everywhere before any budget check can stop it
        raise LoopSpecError(f"spp_budget ({spec.spp_budget:g}) is below spp_first ({spec.spp_first}): the first "
                            "iteration alone renders spp_first samples per pixel; lower spp_first or raise the budget")
    if spec.allocator not in ALLOCATORS:
        raise LoopSpecError(f"unknown allocator {spec.allocator!r}; choose one of {', '.join(ALLOCATORS)}")
    if not isinstance(spec.denoise, bool):
        raise LoopSpecError(f"denoise must be true or false, got {spec.denoise!r}")
    if not _is_number(spec.lam) or lambda_problem(spec.lam):
        raise LoopSpecError(f"lambda: {lambda_problem(spec.lam) or 'must be a number'} (got {spec.lam!r})")
    if not _is_int(spec.seed) or not 0 <= spec.seed <= MAX_SEED:
        raise LoopSpecError(f"seed must be an integer in [0, {MAX_SEED}], got {spec.seed!r}")
    _validate_params(spec.params)
    low, high = PRIORITY_RANGE
    if not _is_int(spec.priority) or not low <= spec.priority <= high:
        raise LoopSpecError(f"priority must be an integer in [{low}, {high}], got {spec.priority!r}")
    _validate_name(spec.name)
    if not spec.denoise and spec.allocator == "error" and spec.max_iterations != 1:
        raise LoopSpecError("the error allocator needs the denoiser; use allocator 'variance' or 'uniform' without it")
    if spec.max_iterations is None and spec.spp_budget is None and spec.time_limit is None and spec.target_error is None:
        raise LoopSpecError("give at least one stopping rule: max_iterations, spp_budget, time_limit or target_error")


def _validate_params(params: dict[str, str]) -> None:
    if not isinstance(params, dict):
        raise LoopSpecError("params must map parameter names to string values")
    if len(params) > MAX_PARAMS:
        raise LoopSpecError(f"at most {MAX_PARAMS} scene parameters")
    for name, value in params.items():
        if not isinstance(name, str) or not PARAM_NAME.match(name):
            raise LoopSpecError(f"scene parameter name {name!r} is not an identifier")
        if not isinstance(value, str) or len(value) > MAX_PARAM_VALUE or "\x00" in value:
            raise LoopSpecError(f"scene parameter {name!r} must be a string of at most {MAX_PARAM_VALUE} characters")


def _validate_name(name: str | None) -> None:
    if name is None:
        return
    if not isinstance(name, str) or not name.strip() or len(name) > MAX_NAME_CHARS or not name.isprintable():
        raise LoopSpecError(f"name must be one printable line of 1 to {MAX_NAME_CHARS} characters, got {name!r}")


def job_name(spec: LoopSpec, bundle_scene: str | None = None) -> str:
    """The name a job is listed under: its own, else the uploaded bundle's entry XML (the
    client sends the bundle's folder or file name), else the built-in scene's name."""
    return spec.name or bundle_scene or spec.scene


def check_limits(spec: LoopSpec, film_width: int, film_height: int, limits: JobLimits = SERVICE_LIMITS) -> None:
    """Refuse a job over the service's caps. `film_width/height` is the effective size: the
    request's, else the scene's own film."""
    width, height = spec.width or film_width, spec.height or film_height
    if max(width, height) > limits.max_side:
        raise LoopSpecError(f"the image is {width}x{height}; each side may be at most {limits.max_side}")
    if width * height > limits.max_pixels:
        raise LoopSpecError(f"the image is {width}x{height} = {width * height} pixels, over the cap of {limits.max_pixels}")
    if spec.frames > limits.max_frames:
        raise LoopSpecError(f"frames may be at most {limits.max_frames}, got {spec.frames}")
    if spec.spp_first > limits.max_spp_first:
        raise LoopSpecError(f"spp_first may be at most {limits.max_spp_first}, got {spec.spp_first}")
    if spec.max_iterations is not None and spec.max_iterations > limits.max_iterations:
        raise LoopSpecError(f"max_iterations may be at most {limits.max_iterations}, got {spec.max_iterations}")
    if spec.time_limit is not None and spec.time_limit > limits.max_time_limit:
        raise LoopSpecError(f"time_limit may be at most {limits.max_time_limit:g} s, got {spec.time_limit:g}")
    memory = estimated_memory(width, height, spec.frames)
    if memory > limits.max_memory_bytes:
        raise LoopSpecError(f"the job would need about {memory / 2**30:.1f} GiB ({width}x{height} × {spec.frames} "
                            f"frame(s)), over this server's cap of {limits.max_memory_bytes / 2**30:.1f} GiB")
    planned = width * height * spec.frames * spec.planned_mean_spp()
    if not math.isfinite(planned):
        # Every iteration doubles the samples: a time limit or target error alone bounds nothing.
        raise LoopSpecError("give max_iterations or spp_budget to bound the total samples")
    if planned > limits.max_total_samples:
        raise LoopSpecError(f"the job would take {planned:.3g} samples ({width}x{height} × {spec.frames} frame(s) × "
                            f"{spec.planned_mean_spp():g} spp), over the cap of {limits.max_total_samples:.3g}")


@dataclass
class IterationRecord:
    """Everything one finished iteration produced, per frame."""

    iteration: int  # 0-based index of the iteration just finished
    buffers: list[FrameBuffer]
    denoised: list[np.ndarray]  # (H, W, 3) float32 each; the noisy mean when not denoising
    error: list[np.ndarray | None]  # (H, W) predicted SMAPE, None when not predicted
    spp_mean: float  # mean samples per pixel over all frames so far
    predicted_error: float | None  # mean of `error`: what --target-error stops on
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage, this iteration
    stop_reason: str | None = None  # set on the last record
    # the error network's own mean before the change calibration (service.loop.change_calibration),
    # over the frames denoised by this loop; None when it predicted none
    network_error: float | None = None
