"""What a render job asks for (LoopSpec) and what each loop iteration hands back (IterationRecord)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.render.framebuffer import FrameBuffer

ALLOCATORS = ("error", "variance", "uniform")
STOP_REASONS = ("max_iterations", "spp_budget", "time_limit", "target_error", "canceled")


@dataclass
class LoopSpec:
    """A render job. `scene` is a built-in scene name or a path to a Mitsuba XML file."""

    scene: str
    width: int | None = None  # None: the scene's own film size
    height: int | None = None
    frames: int = 1
    spp_first: int = 16  # iteration 0, uniform
    max_iterations: int | None = 4
    spp_budget: float | None = None  # mean samples per pixel, all iterations together
    time_limit: float | None = None  # seconds of loop wall time
    target_error: float | None = None  # stop once mean predicted SMAPE <= this
    allocator: str = "error"
    denoise: bool = True
    lam: float = 1.0  # default λ (1 = symmetric loss)
    seed: int = 0


@dataclass
class IterationRecord:
    """Everything one finished iteration produced, per frame."""

    iteration: int  # 0-based index of the iteration just finished
    buffers: list[FrameBuffer]
    denoised: list[np.ndarray]  # (H, W, 3) float32 each; the noisy mean when not denoising
    error: list[np.ndarray | None]  # (H, W) predicted SMAPE, None when not predicted
    spp_mean: float  # mean samples per pixel over all frames so far
    predicted_error: float | None
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage, this iteration
    stop_reason: str | None = None  # set on the last record
