"""The adaptive render loop: render → denoise → predict error → allocate → render …

Iteration 0 renders `spp_first` samples per pixel uniformly; every later iteration doubles
the total (Vogels et al. 2018, §7: "each iteration doubles the sample count") and hands the
new samples out in proportion to the chosen allocator's weights — by default the error
network's per-pixel SMAPE estimate of the current denoised frame.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from models.exposure import Exposure
from models.pretrained import Networks
from service.exr import ExrFrame, result_frame
from service.loop.allocate import (allocate_samples, allocation_weights, edge_top_up, exposed_relative_variance,
                                   iteration_budget)
from service.loop.change_calibration import calibrate_by_change, image_change
from service.loop.denoise_session import DenoiseSession
from service.loop.final_image import blend, raw_share
from service.loop.tensors import nchw, samples_exposure, to_image as to_hwc
from service.loop.spec import IterationRecord, LoopSpec, LoopSpecError, lambda_problem, validate_spec
from service.loop.state import LoopState
from service.render.effects import inspect_frames, load_frames, make_integrator
from service.render.framebuffer import FrameBuffer
from service.render.filters import footprint_pixels
from service.render.object_motion import shape_motion
from service.render.renderer import render_samples
from service.render.runtime import active_variant, mitsuba


def next_counts(allocator: str, buffer: FrameBuffer, predicted_error: np.ndarray | None, budget: int,
                seed: int) -> np.ndarray:
    """The loop's allocation step for one frame: `budget` new samples per the allocator's
    weights. Pixels whose samples all agreed (empty background, flat emitters) gain nothing
    from more: they get only the allocator's uniform floor, once those beside pixels that did
    not agree have EDGE_SETTLE_SPP (allocate.edge_top_up)."""
    # only the variance allocator reads the relative variance (~0.45 s at 2 MP)
    relative = exposed_relative_variance(buffer.mean, buffer.variance) if allocator == "variance" else None
    weights = allocation_weights(allocator, predicted_error=predicted_error, relative_variance=relative,
                                 shape=buffer.shape)
    if allocator == "uniform":
        return allocate_samples(weights, budget, seed=seed)
    converged = buffer.converged()
    top_up = edge_top_up(converged, buffer.settled(), buffer.spp, budget)
    return allocate_samples(weights, budget - int(top_up.sum()), seed=seed, floor_only=converged) + top_up


def exposed_change(previous: np.ndarray, current: np.ndarray, samples: np.ndarray | Exposure) -> float:
    """image_change of two denoised images at the networks' exposure of the samples' mean
    (models.exposure; or that exposure itself): SMAPE's ε is absolute, and the change calibrates
    the error map's mean."""
    exposure = samples if isinstance(samples, Exposure) else Exposure.of(nchw(samples))
    # Exposure.forward's float32 product, taken in the images' own layout (no NCHW round trip)
    scale = np.float32(exposure.scale.flatten()[0].item())
    return image_change(*(np.asarray(x, dtype=np.float32) * scale for x in (previous, current)))


def converged_error(converged: np.ndarray, error: np.ndarray) -> np.ndarray:
    """A converged pixel's mean (FrameBuffer.converged) is exact for what it sees: no error left
    to predict."""
    return np.where(converged, 0.0, error).astype(np.float32)


class IterationInterrupted(RuntimeError):
    """`should_stop` became true inside an iteration: this loop's in-memory state is partial."""


def _scene_label(scene: str, scene_root: Path | None) -> str:
    """The scene as its author names it: a bundle's XML relative to the bundle, never the
    server's path to it (it ends up in every result EXR's header)."""
    if scene_root is None:
        return scene
    try:
        return Path(scene).resolve().relative_to(Path(scene_root).resolve()).as_posix()
    except ValueError:
        return Path(scene).name


@dataclass(frozen=True)
class LambdaPass:
    """One λ edit applied to a loop: the final images, the network passes it ran, and seconds:
    "denoise" the whole re-denoise (the λ tail and the final image), "tail" the λ tail within it."""
    images: list[np.ndarray]
    full_passes: int
    tail_passes: int
    timings: dict[str, float]


class RenderLoop:
    def __init__(self, spec: LoopSpec, networks: Networks | None = None, *, state: LoopState | None = None,
                 scene_root: Path | None = None, owned: range | None = None):
        """`networks`: loaded once by the caller (CLI, server, benchmark); needed when denoising.
        `scene_root`: the folder the scene may read files from (a job's bundle; default: the
        scene file's own folder). `owned`: the frames this loop renders and denoises (default
        all); a sequence fanned out over several workers gives each a share, and the others'
        buffers arrive through `adopt_rendered` / `adopt_denoised` (service.jobs.ray_actor)."""
        validate_spec(spec)
        if spec.denoise and networks is None:
            raise LoopSpecError("denoising needs the networks: pass them (models.pretrained.load_networks)")
        self.spec = spec
        self.scene_label = _scene_label(spec.scene, scene_root)
        # Each frame is loaded once; the effects report reads the loaded frames.
        loaded = load_frames(spec.scene, frames=spec.frames, width=spec.width, height=spec.height, params=spec.params,
                             root=scene_root)
        self.effects = inspect_frames(loaded)
        self.scenes = [frame.scene for frame in loaded]
        # Per frame, how its moving shapes were placed one frame earlier (object motion vectors).
        self.shape_motions = [None] + [shape_motion(mitsuba(), self.scenes[f], self.scenes[f - 1])
                                       if self.effects.animated_shapes else None for f in range(1, len(self.scenes))]
        self.integrator = make_integrator(self.effects)
        film = self.scenes[0].sensors()[0].film()
        width, height = film.crop_size()
        self.state = state or LoopState.new(spec.frames, int(height), int(width), spec.lam)
        if self.state.buffers[0].shape != (height, width) or len(self.state.buffers) != spec.frames:
            raise LoopSpecError("checkpoint does not match the job's resolution or frame count")
        # How far the film filter carries a sample into the neighbours: which agreeing pixels are
        # exact (FrameBuffer.converged). A property of the scene, so a checkpoint needs not keep it.
        footprint = footprint_pixels(film.rfilter().radius())
        for buffer in self.state.buffers:
            buffer.footprint = footprint
        # One frame → no temporal work; more → each frame's 2M+1 window (all frames advance together).
        radius = networks.denoiser.config.temporal_radius if (networks and self.effects.temporal) else 0
        self.owned = owned if owned is not None else range(spec.frames)
        self.session = DenoiseSession(networks, spec.frames, radius, self.owned) if spec.denoise else None
        self.lock = self.session.lock if self.session else threading.RLock()
        self._denoised: list[np.ndarray | None] = [None] * spec.frames
        # the final images (`final_image`): `_denoised` falling back towards the raw image; None: not composed yet
        self._final: list[np.ndarray] | None = None
        # per frame, the raw image's share of the final image (final_image.raw_share), from the samples,
        # the error map and the first denoised image composed after the pass; a λ edit keeps it, as
        # it keeps the error map. None: not computed yet
        self._raw_share: list[np.ndarray | None] = [None] * spec.frames
        self._raw_image: list[np.ndarray | None] = [None] * spec.frames  # buffer.raw, beside `_raw_share`
        self._denoised_lam: np.ndarray | None = None  # the λ map `_denoised` was made with
        self._denoised_samples: list[int | None] = [None] * spec.frames  # the frame's sample total behind it
        # per frame, how far its denoised image moved since the previous iteration (None: unknown),
        # and the error network's own mean before that rescales it (service.loop.change_calibration)
        self._change: list[float | None] = [None] * spec.frames
        self._network_means: list[float | None] = [None] * spec.frames
        # the buffers after the first half of iteration 0, when it is split (`_splits_first_iteration`)
        self._first_half: list[FrameBuffer] | None = None
        self._converged: list[np.ndarray] = [np.zeros(self.state.buffers[0].shape, bool) for _ in range(spec.frames)]

    # -- the loop ---------------------------------------------------------------------------

    def run(self, should_stop: Callable[[], bool] = lambda: False) -> Iterator[IterationRecord]:
        """Yield one record per finished iteration; the last one carries the stop reason.

        Returns without a record when `should_stop()` is true before an iteration starts.
        """
        while not self.done() and not should_stop():
            started = time.perf_counter()
            timings: dict[str, float] = {}
            self.render_step(timings, should_stop)
            self.denoise_step(timings)
            record = self.finish_step(timings, time.perf_counter() - started, should_stop)
            yield record
            if record.stop_reason is not None:
                return

    # -- the steps of one iteration (a fanned-out sequence runs them one by one, exchanging
    #    frames between them) -------------------------------------------------------------

    def done(self) -> bool:
        """Whether a stop rule was already met (a resumed job that finished does not render again)."""
        return self._stop_before_next() is not None

    def render_step(self, timings: dict, should_stop: Callable[[], bool] = lambda: False) -> None:
        """Allocate and render the new samples of the owned frames."""
        self._render(self._allocate(timings), timings, should_stop)

    def finish_step(self, timings: dict, seconds: float, should_stop: Callable[[], bool] = lambda: False
                    ) -> IterationRecord:
        """Count the iteration and apply the stop rules; the record of what it produced.
        Composing the final images (service.loop.final_image: raw image, its share, blend) is the
        iteration's last piece of work, after the error network: its seconds count in the denoise
        stage and the loop's clock, as OIDN's call counts in a `mi.render` + OIDN image's time."""
        with self.lock:
            self.state.iteration += 1
        started = time.perf_counter()
        self.denoised()
        composed = time.perf_counter() - started
        if self.session is not None:
            timings["denoise"] = timings.get("denoise", 0.0) + composed
        with self.lock:
            self.state.elapsed += seconds + composed
        record = self._record(timings)
        record.stop_reason = self._stop_after(record)
        if record.stop_reason is None and should_stop():
            record.stop_reason = "canceled"
        return record

    def adopt_rendered(self, buffers: dict[int, FrameBuffer]) -> None:
        """Frames rendered elsewhere this iteration (the denoiser's temporal window reads them)."""
        with self.lock:
            for f, buffer in buffers.items():
                self.state.buffers[f] = buffer
            self._forget_final()

    def adopt_denoised(self, frames: dict[int, tuple[np.ndarray, np.ndarray | None, np.ndarray]]) -> None:
        """Frames denoised elsewhere this iteration: (denoised image, predicted error, converged mask)."""
        with self.lock:
            for f, (image, error, converged) in frames.items():
                self._denoised[f], self.state.error_maps[f], self._converged[f] = image, error, converged
            self._forget_final()

    def owned_outputs(self) -> dict[int, tuple[np.ndarray, np.ndarray | None, np.ndarray]]:
        """This loop's frames as `adopt_denoised` takes them."""
        with self.lock:
            return {f: (self._denoised[f], self.state.error_maps[f], self._converged[f]) for f in self.owned}

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

    def _allocate(self, timings: dict) -> dict[int, np.ndarray]:
        t0 = time.perf_counter()
        spec, state = self.spec, self.state
        counts: dict[int, np.ndarray] = {}
        for f in self.owned:
            buf = state.buffers[f]
            if state.iteration == 0:
                counts[f] = np.full(buf.shape, spec.spp_first, dtype=np.int64)
                continue
            budget = iteration_budget(int(buf.spp.sum()))
            if spec.spp_budget is not None:
                budget = min(budget, max(0, int(round(spec.spp_budget * buf.spp.size)) - int(buf.spp.sum())))
            counts[f] = next_counts(spec.allocator, buf, state.error_maps[f], budget,
                                    seed=spec.seed * 1000 + state.iteration)
        timings["allocate"] = time.perf_counter() - t0
        return counts

    def _render(self, counts: dict[int, np.ndarray], timings: dict, should_stop: Callable[[], bool]) -> None:
        t0 = time.perf_counter()

        def check(_samples: int) -> None:
            # Called after every wavefront chunk: a cancel or shutdown takes effect within one
            # chunk. The buffers are then half-updated, so the caller must drop this loop and
            # resume from the last checkpoint.
            if should_stop():
                raise IterationInterrupted("stopped inside an iteration; resume from the last checkpoint")

        split = self._splits_first_iteration()
        parts = [{f: c // 2 for f, c in counts.items()}, {f: c - c // 2 for f, c in counts.items()}] if split else [counts]
        for part, part_counts in enumerate(parts):
            if part == 1:
                self._first_half = [buffer.copy() for buffer in self.state.buffers]
            for f, frame_counts in part_counts.items():
                if f >= len(self.scenes):
                    break  # a scene without `$frame` is one frame (load_frames)
                prev = self.scenes[f - 1].sensors()[0] if (f > 0 and self.effects.motion_vectors) else None
                render_samples(self.scenes[f], frame_counts, self.state.buffers[f], integrator=self.integrator,
                               seed=self.spec.seed * 7919 + f, prev_sensor=prev, prev_shapes=self.shape_motions[f],
                               progress=check)
        timings["render"] = time.perf_counter() - t0

    def _splits_first_iteration(self) -> bool:
        """Whether iteration 0 renders in two halves and the first half is denoised too, so that the
        first mean is also calibrated by the image's change (service.loop.change_calibration). Only
        for a job that stops on its target error, the one use of that mean (the others pay
        nothing), with an error network that carries a change scale, an even `spp_first` and
        every frame owned by this loop (the halves' temporal windows must all be here)."""
        return (self.state.iteration == 0 and self.spec.target_error is not None and self.session is not None
                and self.session.networks.error_predictor.change_scale is not None
                and self.spec.spp_first % 2 == 0 and len(self.owned) == self.spec.frames)

    def denoise_step(self, timings: dict) -> None:
        """Denoise the owned frames and predict their error (their temporal windows read the
        neighbours' buffers of this iteration, adopted beforehand when not owned)."""
        timings["denoise"] = timings["error"] = 0.0
        self._forget_final()
        if self.session is None:
            with self.lock:
                for f in self.owned:
                    self._denoised[f] = self.state.buffers[f].raw  # --no-denoise: the splatted raw image
            return
        t0 = time.perf_counter()
        with self.lock:
            lam_map = self.state.lam_map.copy()
        if self._first_half is not None:
            first_half, self._first_half = self._first_half, None
            self._denoise_first_half(first_half, lam_map)
        images = self.session.denoise(self.state.buffers, lam_map)
        t1 = time.perf_counter()
        errors = self.session.predict_error(images)
        t2 = time.perf_counter()
        with self.lock:
            for f in self.owned:
                self._converged[f] = self.state.buffers[f].converged()
                self.state.error_maps[f] = converged_error(self._converged[f], errors[f])
                self._network_means[f] = float(self.state.error_maps[f].mean())
            previous_lam = self._denoised_lam
            previous = {f: (self._denoised[f], self._denoised_samples[f]) for f in self.owned}
            # A λ edit that arrived meanwhile wins over the map this pass started with.
            self._keep_converged(self.session.relambda(self.state.lam_map) if not np.array_equal(lam_map, self.state.lam_map)
                                 else {f: to_hwc(image) for f, image in images.items()})
            self._calibrate_by_change(previous, previous_lam)
        timings["denoise"], timings["error"] = t1 - t0, t2 - t1

    def _calibrate_by_change(self, previous: dict[int, tuple[np.ndarray | None, int | None]],
                             previous_lam: np.ndarray | None) -> None:
        """Rescale each owned frame's new error map by how far its denoised image moved from the
        one before (service.loop.change_calibration). `previous`: per frame, that image and the
        sample total behind it; only an image of half the samples, made with the same λ map, counts."""
        same_lam = previous_lam is not None and np.array_equal(previous_lam, self.state.lam_map)
        scale = self.session.networks.error_predictor.change_scale
        for f, (image, samples) in previous.items():
            now = self._denoised_samples[f] = int(self.state.buffers[f].spp.sum())
            if samples is not None and 2 * samples == now:        # the previous iteration's image
                self._change[f] = (exposed_change(image, self._denoised[f], samples_exposure(self.state.buffers[f]))
                                   if same_lam else None)
            elif samples != now:                                  # none (first pass, resumed loop)
                self._change[f] = None
            # (the same samples again: a repeated pass keeps the change it measured first)
            self.state.error_maps[f] = calibrate_by_change(self.state.error_maps[f], self._change[f], scale)
        self._forget_final()

    def _denoise_first_half(self, buffers: list[FrameBuffer], lam_map: np.ndarray) -> None:
        """Denoise the first half of a split iteration 0 and keep it as the image the full one's
        change is measured against."""
        images = self.session.denoise(buffers, lam_map)
        with self.lock:
            for f in self.owned:
                kept = buffers[f].converged()[..., None]
                self._denoised[f] = np.where(kept, buffers[f].mean, to_hwc(images[f])).astype(np.float32)
                self._denoised_samples[f] = int(buffers[f].spp.sum())
            self._denoised_lam = lam_map.copy()

    # -- λ without re-rendering -----------------------------------------------------------

    def set_lambda(self, lam_map: np.ndarray) -> list[np.ndarray]:
        """Re-denoise every (owned) frame with a new per-pixel λ from cached pre-λ features."""
        lam_map = np.asarray(lam_map, dtype=np.float32)
        if lam_map.shape != self.state.lam_map.shape:
            raise LoopSpecError(f"λ map is {lam_map.shape[::-1]}, the image is {self.state.lam_map.shape[::-1]}")
        problem = lambda_problem(lam_map)
        if problem:
            raise LoopSpecError(problem)
        with self.lock:
            self.state.lam_map = lam_map.copy()
            if self.state.iteration == 0:
                return []
            if self.session is None:
                return list(self._denoised)
            if not self.session.has_features:
                self.denoise_step({})  # after a restart the features are rebuilt once
            self._keep_converged(self.session.relambda(lam_map))
            return self.denoised()

    def counted_set_lambda(self, lam_map: np.ndarray) -> "LambdaPass":
        """`set_lambda`, with the network passes it ran and its seconds (what a λ edit reports)."""
        session = self.session
        before = (session.full_calls, session.tail_calls, session.tail_seconds) if session else (0, 0, 0.0)
        started = time.perf_counter()
        images = self.set_lambda(lam_map)
        seconds = time.perf_counter() - started
        after = (session.full_calls, session.tail_calls, session.tail_seconds) if session else before
        return LambdaPass(images, after[0] - before[0], after[1] - before[1],
                          {"denoise": seconds, "tail": after[2] - before[2]})

    def _keep_converged(self, images: dict[int, np.ndarray]) -> None:
        """Store the owned frames' denoised images. Pixels whose samples all agreed
        (FrameBuffer.converged) keep their exact mean: filtering could only bleed neighbours'
        light into them."""
        for f, image in images.items():
            mask, buf = self._converged[f], self.state.buffers[f]
            # the np.where is a full-frame pass: only when a pixel needs it
            kept = np.where(mask[..., None], buf.mean, image) if mask.any() else image
            self._denoised[f] = kept.astype(np.float32)
        self._denoised_lam = self.state.lam_map.copy()
        self._final = None

    # -- outputs ----------------------------------------------------------------------------

    def denoised(self) -> list[np.ndarray]:
        """The final images: denoised, each pixel falling back towards the raw image where the
        samples alone are expected to be closer (service.loop.final_image)."""
        with self.lock:
            if self.state.iteration > 0 and any(d is None for d in self._denoised):
                self.denoise_step({})
            if self._final is None:
                self._final = [self._compose_final(f) for f in range(len(self._denoised))]
            return list(self._final)

    def denoised_only(self) -> list[np.ndarray | None]:
        """The denoised images before the final composition falls back towards the raw image."""
        with self.lock:
            return list(self._denoised)

    def _forget_final(self) -> None:
        """The samples or the error maps changed: the final images and the raw image's shares go."""
        self._final = None
        self._raw_share = [None] * len(self._raw_share)
        self._raw_image = [None] * len(self._raw_image)

    def _compose_final(self, f: int) -> np.ndarray | None:
        """Frame f's final image; the denoised one as it is without an error map (or without
        denoising: then `_denoised` is the raw image already)."""
        image, error, buffer = self._denoised[f], self.state.error_maps[f], self.state.buffers[f]
        if self.session is None or image is None or error is None:
            return image
        if self._raw_share[f] is None:
            exposure = float(samples_exposure(buffer).scale.flatten()[0])
            # kept with its share, which a λ edit recomposes from; the buffer keeps the raw image
            # and its variance for the pass too (FrameBuffer.raw_and_variance)
            self._raw_image[f], raw_variance = buffer.raw_and_variance()
            self._raw_share[f] = raw_share(self._raw_image[f], image, raw_variance, error, exposure)
        return blend(image, self._raw_image[f], self._raw_share[f])

    def _record(self, timings: dict, images: bool = True) -> IterationRecord:
        state = self.state
        known = [e for e in state.error_maps if e is not None]
        network_means = [m for m in self._network_means if m is not None]
        return IterationRecord(
            iteration=state.iteration - 1,
            buffers=state.buffers,
            denoised=self.denoised() if images else [],
            error=list(state.error_maps),
            spp_mean=state.spp_mean,
            predicted_error=float(np.mean([e.mean() for e in known])) if known else None,
            network_error=float(np.mean(network_means)) if network_means else None,
            timings=dict(timings),
        )

    def result_frames(self) -> list[ExrFrame]:
        """One ExrFrame per frame in the project layout (built by service.exr)."""
        images = self.denoised()
        header = {"scene": self.scene_label, "iteration": self.state.iteration, "variant": active_variant()}
        return [
            result_frame(buf, images[f] if images else buf.raw, error=self.state.error_maps[f],
                         lam=self.state.lam_map if self.spec.denoise else None, header={**header, "frame": f})
            for f, buf in enumerate(self.state.buffers)
        ]
