"""The adaptive render loop: render → denoise → predict error → allocate → render …

Iteration 0 renders `spp_first` samples per pixel uniformly; every later iteration doubles
the total (Vogels et al. 2018, §7: "each iteration doubles the sample count") and hands the
new samples out in proportion to the chosen allocator's weights — by default the error
network's per-pixel SMAPE estimate of the current denoised frame.
"""
from __future__ import annotations

import threading
import time
from typing import Callable, Iterator

import numpy as np
import torch

from service.exr import ExrFrame
from service.loop.allocate import allocate_samples, allocation_weights, iteration_budget
from service.loop.denoise import configure_torch_threads, frame_tensors, lam_tensor, temporal_window, to_image
from service.loop.spec import ALLOCATORS, IterationRecord, LoopSpec
from service.loop.state import LoopState
from service.render.effects import inspect_frames, load_frames, make_integrator
from service.render.renderer import render_samples
from service.render.runtime import active_variant


class LoopSpecError(ValueError):
    """A job asks for something the loop cannot do; the message says what."""


def validate_spec(spec: LoopSpec) -> None:
    if spec.allocator not in ALLOCATORS:
        raise LoopSpecError(f"unknown allocator {spec.allocator!r}; choose one of {', '.join(ALLOCATORS)}")
    if spec.frames < 1:
        raise LoopSpecError("frames must be >= 1")
    if spec.spp_first < 1:
        raise LoopSpecError("spp_first must be >= 1")
    if spec.max_iterations is not None and spec.max_iterations < 1:
        raise LoopSpecError("max_iterations must be >= 1")
    for name in ("spp_budget", "time_limit", "target_error"):
        value = getattr(spec, name)
        if value is not None and not value > 0:
            raise LoopSpecError(f"{name} must be > 0")
    if not 1.0 <= spec.lam <= 10.0:
        raise LoopSpecError("lambda must lie in [1, 10]")
    if not spec.denoise and spec.allocator == "error" and spec.max_iterations != 1:
        raise LoopSpecError("the error allocator needs the denoiser; use allocator 'variance' or 'uniform' without it")
    if spec.max_iterations is None and spec.spp_budget is None and spec.time_limit is None and spec.target_error is None:
        raise LoopSpecError("give at least one stopping rule: max_iterations, spp_budget, time_limit or target_error")


class RenderLoop:
    def __init__(self, spec: LoopSpec, *, state: LoopState | None = None, denoiser=None, error_predictor=None):
        validate_spec(spec)
        configure_torch_threads()
        self.spec = spec
        # Each frame is loaded once; the effects report reads the loaded frames.
        loaded = load_frames(spec.scene, frames=spec.frames, width=spec.width, height=spec.height)
        self.effects = inspect_frames(loaded)
        self.scenes = [frame.scene for frame in loaded]
        self.integrator = make_integrator(self.effects)
        width, height = self.scenes[0].sensors()[0].film().crop_size()
        self.state = state or LoopState.new(spec.frames, int(height), int(width), spec.lam)
        if self.state.buffers[0].shape != (height, width) or len(self.state.buffers) != spec.frames:
            raise LoopSpecError("checkpoint does not match the job's resolution or frame count")
        self.denoiser, self.error_predictor = denoiser, error_predictor
        if spec.denoise and denoiser is None:
            from models.pretrained import load_default_denoiser, load_default_error_predictor

            self.denoiser, self.error_predictor = load_default_denoiser(), load_default_error_predictor()
        self._caches: list = [None] * spec.frames  # pre-λ features per frame (models.Denoiser.prepare)
        self._denoised: list[np.ndarray | None] = [None] * spec.frames
        self._lock = threading.RLock()
        self.full_calls = 0  # full denoiser forward passes (prepare + apply)
        self.tail_calls = 0  # λ-only re-runs from cached features

    # -- the loop ---------------------------------------------------------------------------

    def run(self, should_stop: Callable[[], bool] = lambda: False) -> Iterator[IterationRecord]:
        """Yield one record per finished iteration; the last one carries the stop reason.

        Returns without a record when `should_stop()` is true before an iteration starts.
        """
        while True:
            reason = self._stop_before_next()
            if reason is not None:
                return
            if should_stop():
                return
            started = time.perf_counter()
            timings = {}
            counts = self._allocate(timings)
            self._render(counts, timings)
            self._denoise_and_predict(timings)
            with self._lock:
                self.state.iteration += 1
                self.state.elapsed += time.perf_counter() - started
            record = self._record(timings)
            record.stop_reason = self._stop_after(record)
            if record.stop_reason is None and should_stop():
                record.stop_reason = "canceled"
            yield record
            if record.stop_reason is not None:
                return

    def _stop_before_next(self) -> str | None:
        """A resumed job that had already met its stop rule does not render again."""
        if self.state.iteration == 0:
            return None
        return self._stop_after(self._record({}, images=False))

    def _stop_after(self, record: IterationRecord) -> str | None:
        spec, state = self.spec, self.state
        if spec.max_iterations is not None and state.iteration >= spec.max_iterations:
            return "max_iterations"
        if spec.spp_budget is not None and state.spp_mean >= spec.spp_budget - 1e-9:
            return "spp_budget"
        if spec.target_error is not None and record.predicted_error is not None and record.predicted_error <= spec.target_error:
            return "target_error"
        if spec.time_limit is not None:
            # The next iteration renders as many samples as all earlier ones together, so it
            # takes about as long as they did: stop if it would overrun the limit.
            if 2 * state.elapsed > spec.time_limit:
                return "time_limit"
        return None

    def _allocate(self, timings: dict) -> list[np.ndarray]:
        t0 = time.perf_counter()
        spec, state = self.spec, self.state
        counts = []
        for f, buf in enumerate(state.buffers):
            pixels = buf.spp.size
            if state.iteration == 0:
                budget = spec.spp_first * pixels
            else:
                budget = iteration_budget(int(buf.spp.sum()))
            if spec.spp_budget is not None:
                budget = min(budget, max(0, int(round(spec.spp_budget * pixels)) - int(buf.spp.sum())))
            if state.iteration == 0:
                counts.append(np.full(buf.shape, spec.spp_first, dtype=np.int64))
                continue
            weights = allocation_weights(
                spec.allocator,
                predicted_error=state.error_maps[f],
                relative_variance=buf.relative_variance(),
                shape=buf.shape,
            )
            counts.append(allocate_samples(weights, budget, seed=spec.seed * 1000 + state.iteration))
        timings["allocate"] = time.perf_counter() - t0
        return counts

    def _render(self, counts: list[np.ndarray], timings: dict) -> None:
        t0 = time.perf_counter()
        for f, (scene, buf) in enumerate(zip(self.scenes, self.state.buffers)):
            prev = self.scenes[f - 1].sensors()[0] if (f > 0 and self.effects.motion_vectors) else None
            render_samples(scene, counts[f], buf, integrator=self.integrator, seed=self.spec.seed * 7919 + f, prev_sensor=prev)
        timings["render"] = time.perf_counter() - t0

    @torch.no_grad()
    def _denoise_and_predict(self, timings: dict) -> None:
        timings["denoise"] = timings["error"] = 0.0
        if not self.spec.denoise:
            with self._lock:
                self._denoised = [b.mean for b in self.state.buffers]
            return
        t0 = time.perf_counter()
        tensors = [frame_tensors(b) for b in self.state.buffers]
        # One frame → no temporal work; more → each frame's 2M+1 window (all frames advance together).
        radius = self.denoiser.config.temporal_radius if self.effects.temporal else 0
        caches, images = [], []
        with self._lock:
            lam = lam_tensor(self.state.lam_map)
        for f in range(len(tensors)):
            indices, centre = temporal_window(f, len(tensors), radius)
            cache = self.denoiser.prepare([tensors[i] for i in indices], centre)
            caches.append(cache)
            images.append(self.denoiser.apply(cache, lam))
            self.full_calls += 1
        t1 = time.perf_counter()
        errors = [to_image(self.error_predictor(t, img)) for t, img in zip(tensors, images)]
        t2 = time.perf_counter()
        with self._lock:
            self._caches = caches
            self._denoised = [to_image(img) for img in images]
            self.state.error_maps = errors
        timings["denoise"], timings["error"] = t1 - t0, t2 - t1

    # -- λ without re-rendering -----------------------------------------------------------

    @torch.no_grad()
    def set_lambda(self, lam_map: np.ndarray) -> list[np.ndarray]:
        """Re-denoise every frame with a new per-pixel λ from cached pre-λ features."""
        lam_map = np.asarray(lam_map, dtype=np.float32)
        if lam_map.shape != self.state.lam_map.shape:
            raise LoopSpecError(f"λ map is {lam_map.shape[::-1]}, the image is {self.state.lam_map.shape[::-1]}")
        if not np.isfinite(lam_map).all() or lam_map.min() < 1 or lam_map.max() > 10:
            raise LoopSpecError("λ values must be finite and lie in [1, 10]")
        with self._lock:
            self.state.lam_map = lam_map.copy()
            if not self.spec.denoise or self.state.iteration == 0:
                return [] if self.state.iteration == 0 else list(self._denoised)
            if any(c is None for c in self._caches):
                self._denoise_and_predict({})  # after a restart the cache is rebuilt once
            lam = lam_tensor(lam_map)
            images = []
            for cache in self._caches:
                images.append(to_image(self.denoiser.apply(cache, lam)))
                self.tail_calls += 1
            self._denoised = images
            return list(images)

    @property
    def uses_cached_features(self) -> bool:
        return self.tail_calls > 0

    # -- outputs ----------------------------------------------------------------------------

    def denoised(self) -> list[np.ndarray]:
        with self._lock:
            if self.state.iteration > 0 and any(d is None for d in self._denoised):
                self._denoise_and_predict({})
            return list(self._denoised)

    def _record(self, timings: dict, images: bool = True) -> IterationRecord:
        state = self.state
        errors = state.error_maps
        known = [e for e in errors if e is not None]
        return IterationRecord(
            iteration=state.iteration - 1,
            buffers=state.buffers,
            denoised=self.denoised() if images else [],
            error=list(errors),
            spp_mean=state.spp_mean,
            predicted_error=float(np.mean([e.mean() for e in known])) if known else None,
            timings=dict(timings),
        )

    def result_frames(self) -> list[ExrFrame]:
        """One ExrFrame per frame in the project layout (DESIGN.md)."""
        images = self.denoised()
        frames = []
        for f, buf in enumerate(self.state.buffers):
            frames.append(ExrFrame(
                color=images[f] if images else buf.mean,
                noisy=buf.mean, variance=buf.variance, albedo=buf.albedo, normal=buf.normal,
                depth=buf.depth, motion=buf.motion, spp=buf.spp.astype(np.uint32),
                error=self.state.error_maps[f], extra=buf.aov_layers(),
                lam=self.state.lam_map if self.spec.denoise else None,
                header={"scene": self.spec.scene, "iteration": self.state.iteration,
                        "total_samples": int(buf.spp.sum()), "variant": active_variant(), "frame": f},
            ))
        return frames
