"""The measurements of `renderloop bench --versus-mitsuba`: error-vs-wall-time curves of
`mi.render` + OIDN (the scene's filter, and a box film), of the render loop (error allocator) and of
uniform sampling + our denoiser, each with its peak RSS; and the equal-error / equal-time reading
of two curves that the report's headline rests on.

Wall time of a `mi.render` point: one render of N spp (the scene loaded once, its kernels compiled
by an untimed warm-up) plus the OIDN call. Wall time of a loop point: the loop's own per-stage
timings summed over its iterations so far (render, denoise with the final image's composition,
error, allocate), after the networks
were warmed by an untimed one-iteration loop and the timed loop's own kernels built by three
untimed passes (`compile_loop_kernels`). Each method's kernel compile time is kept
beside its curve (`kernel_compile_seconds`): a user's first render of a scene pays it.
"""
from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from bench.common import OidnDenoise, Reference, recorded_kernels, sanitize
from bench.dev_references import DevScene
from bench.loop_run import EXTRAPOLATION_LIMIT, LOOP_SEED, STAGES, NoErrorPrediction
from bench.versus_mitsuba_scene import Film, competitor_scene, render_with_aovs, warm_up
from models.losses import smape
from models.metrics import RELMSE_EPS
from models.pretrained import Networks
from service.loop.loop import RenderLoop
from service.loop.spec import IterationRecord, LoopSpec
from service.loop.tensors import nchw
from service.render.renderer import render_samples

FIRST_SPP = 16
MITSUBA_SEED = 1_000  # any stream but the reference's (bench.common.REFERENCE_SEED)
RSS_INTERVAL_S = 0.02
# Binary digits 0, 2, …, 10 set: a pixel with this count takes every sequence length 1, 4, …, 1024
# of a stratifying scene's digit groups (service/render/stratified_lanes.py), whose sampler is
# built with that length as its sample count, a literal in the kernel. Counts above 4095 in one
# pass (rare) still compile theirs when they occur.
WARM_UP_COUNT = 0b10101010101


@dataclass
class CurvePoint:
    spp: float  # mean samples per pixel
    seconds: float  # wall time to this image (see the module docstring)
    smape: float
    stages: dict[str, float]  # seconds per stage of this point (a loop: this iteration's)
    relmse: float = math.nan  # relMSE with the reference's own noise taken out (`debiased_relmse`)


@dataclass
class Curve:
    key: str
    label: str
    points: list[CurvePoint] = field(default_factory=list)
    peak_rss_mb: float = math.nan  # the process's peak resident memory while this curve ran
    rss_growth_mb: float = math.nan  # that peak minus the resident memory when it started
    compile_s: float = math.nan  # Dr.Jit's kernel compile time in this method's untimed warm-up

    @property
    def seconds(self) -> list[float]:
        return [p.seconds for p in self.points]

    @property
    def errors(self) -> list[float]:
        return [p.smape for p in self.points]


def spp_levels(max_spp: int) -> list[int]:
    """16, 32, … up to max_spp (the loop doubles its total each iteration; `mi.render` matches)."""
    levels, spp = [], FIRST_SPP
    while spp <= max_spp:
        levels.append(spp)
        spp *= 2
    if not levels:
        raise ValueError(f"--max-spp must be at least {FIRST_SPP}, got {max_spp}")
    return levels


def image_smape(image: np.ndarray, reference: np.ndarray) -> float:
    """SMAPE (ε = 0.01) on linear radiance, sanitised as every report's metrics are."""
    return float(smape(sanitize(nchw(image)), sanitize(nchw(reference))))


def debiased_relmse(image: np.ndarray, reference: Reference) -> float:
    """relMSE (ε = RELMSE_EPS) against a noisy reference with its noise taken out. For a
    reference mean m independent of the image x, E[(x − m)²] = (x − t)² + Var(m): each pixel's
    squared difference less the reference's variance of the mean (its passes' spread,
    bench.common.Reference) estimates the squared error against the truth t without bias. The
    denominator keeps m² + ε: its noise is second order where (σ_m / m)² ≲ 1e-3, most scenes at
    1024 spp, but not where light arrives by rare paths (fog_spot's reference: relative error 0.10,
    its typical pixel below the truth), and there both metrics lean towards images that drop those
    paths' energy (docs/decisions.md, "fog_spot at 2 MP"). Unlike SMAPE, whose floor a noisy
    reference sets, this reads errors below the reference's own; it can be ≤ 0 where the image is
    closer to the truth than the reference's noise can tell."""
    x = np.nan_to_num(np.asarray(image, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    np.maximum(x, 0.0, out=x)
    m = np.asarray(reference.mean, dtype=np.float64)
    x -= m
    np.square(x, out=x)
    x -= reference.variance
    x /= np.square(m) + RELMSE_EPS
    return float(x.mean())


# --- peak memory ----------------------------------------------------------------------------------


def resident_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


@contextmanager
def peak_rss(curve: Curve) -> Iterator[None]:
    """Sample this process's resident memory every RSS_INTERVAL_S on a thread while the block runs
    (getrusage's ru_maxrss is the whole process's lifetime peak, so it cannot tell methods apart)."""
    start = peak = resident_mb()
    done = threading.Event()

    def sample() -> None:
        nonlocal peak
        while not done.wait(RSS_INTERVAL_S):
            peak = max(peak, resident_mb())

    sampler = threading.Thread(target=sample, name="peak-rss", daemon=True)
    sampler.start()
    try:
        yield
    finally:
        done.set()
        sampler.join()
        peak = max(peak, resident_mb())
        curve.peak_rss_mb, curve.rss_growth_mb = peak, peak - start


# --- mi.render + OIDN -------------------------------------------------------------------------------


def mitsuba_curve(scene: DevScene, film: Film, box: bool, levels: list[int], reference: Reference,
                  oidn: OidnDenoise) -> Curve:
    """`mi.render` at each uniform spp, with its albedo and normals from a second render
    (versus_mitsuba_scene.render_with_aovs), then OIDN: one point per spp."""
    loaded = competitor_scene(scene, film, box)
    curve = Curve("mitsuba-box" if box else "mitsuba",
                  "`mi.render` + OIDN, box film" if box else "`mi.render` + OIDN, the scene's filter")
    with kernel_compile_seconds() as compiled:  # compiles the kernels, untimed
        warm_up(loaded, levels, MITSUBA_SEED - 1)
    curve.compile_s = compiled[0]
    with peak_rss(curve):
        for spp in levels:
            started = time.perf_counter()
            image = render_with_aovs(loaded, spp, MITSUBA_SEED)
            rendered = time.perf_counter()
            denoised = oidn(image.color, image.albedo, image.normal)
            done = time.perf_counter()
            stages = {"render": rendered - started, "oidn": done - rendered}
            curve.points.append(CurvePoint(spp, done - started, image_smape(denoised, reference.mean), stages,
                                           debiased_relmse(denoised, reference)))
    return curve


# --- the render loop --------------------------------------------------------------------------------


@dataclass
class LoopRun:
    curve: Curve
    loop: RenderLoop  # kept: the fixed-cost measurements read its final state
    last: IterationRecord


def make_loop(scene: DevScene, film: Film, networks: Networks, allocator: str, iterations: int,
              seed: int = LOOP_SEED) -> RenderLoop:
    """The loop as a job runs it, on the scene as written at `film`'s size; uniform allocation
    does not pay for the error network."""
    spec = LoopSpec(scene=str(scene.path), width=film.width, height=film.height, spp_first=FIRST_SPP,
                    max_iterations=iterations, allocator=allocator, denoise=True, seed=seed)
    predictor = networks.error_predictor if allocator == "error" else NoErrorPrediction()
    return RenderLoop(spec, Networks(networks.denoiser, predictor))


def warm_up_loop(scene: DevScene, film: Film, networks: Networks) -> None:
    """One untimed iteration: oneDNN (or cuDNN) builds the networks' primitives. Its kernels are
    not the timed loop's: Dr.Jit builds a scene's kernels per load (`compile_loop_kernels`)."""
    for _ in make_loop(scene, film, networks, "error", 1).run():
        pass


def compile_loop_kernels(loop: RenderLoop) -> None:
    """Render three passes of `loop`'s own frame-0 scene into a copy of its buffer, so that
    Dr.Jit builds every kernel the loop's iterations launch before it is timed, as `mi.render`'s
    warm-up does for each sample count. Kernels are per scene *load*: a loaded scene's objects
    reach them as literals (registry ids, offsets into its call tables), so a warm-up on another
    load of the same file builds other kernels. The passes: the first iteration's (`spp_first`
    everywhere: the uniform lane map, and a film filter's splat into an empty buffer, a kernel of
    its own); two neighbouring pixels with one count, and two pixels apart (lane_map.py: the
    uniform and the uneven lane map of a stratifying scene's digit groups, every sequence length
    to 1024 — stratified_lanes.py, WARM_UP_COUNT). On a GPU, where OptiX builds each new kernel,
    these compiles were most of the loop's render time (docs/gpu.md)."""
    buffer = loop.state.buffers[0].copy()
    passes = [np.full(buffer.spp.shape, loop.spec.spp_first, dtype=np.int64)]
    for pixels in ((0, 1), (0, 2)):
        counts = np.zeros(buffer.spp.shape, dtype=np.int64)
        counts.flat[list(pixels)] = WARM_UP_COUNT
        passes.append(counts)
    for counts in passes:
        render_samples(loop.scenes[0], counts, buffer, integrator=loop.integrator, seed=loop.spec.seed * 7919,
                       prev_shapes=loop.shape_motions[0])


@contextmanager
def kernel_compile_seconds() -> Iterator[list[float]]:
    """Seconds Dr.Jit spent building kernels (its backend's compile of each kernel that no cache
    held: LLVM, or CUDA/OptiX) while the block ran; yields a one-element list filled on exit."""
    result = [math.nan]
    with recorded_kernels() as kernels:
        yield result
    result[0] = sum(k.get("backend_time", 0.0) for k in kernels
                    if k.get("type") == dr.KernelType.JIT and not k.get("cache_hit")) / 1000.0


def loop_curve(key: str, label: str, scene: DevScene, film: Film, networks: Networks, allocator: str,
               levels: list[int], reference: Reference | None) -> LoopRun:
    """One point per iteration (16, 32, … spp mean): cumulative stage time, SMAPE and debiased
    relMSE (nan without a reference: a run for its costs and memory only)."""
    curve = Curve(key, label)
    loop = make_loop(scene, film, networks, allocator, len(levels))
    with kernel_compile_seconds() as compiled:  # untimed, as mi.render's warm-up
        compile_loop_kernels(loop)
    curve.compile_s = compiled[0]
    elapsed, last = 0.0, None
    with peak_rss(curve):
        for record in loop.run():
            stages = {name: float(record.timings.get(name, 0.0)) for name in STAGES}
            elapsed += sum(stages.values())
            error = math.nan if reference is None else image_smape(record.denoised[0], reference.mean)
            relative = math.nan if reference is None else debiased_relmse(record.denoised[0], reference)
            curve.points.append(CurvePoint(record.spp_mean, elapsed, error, stages, relative))
            last = record
    return LoopRun(curve, loop, last)


# --- reading two curves against each other -----------------------------------------------------------


@dataclass(frozen=True)
class Reading:
    """A value read off a curve and how: "interpolated" (log-log, between two measured points),
    "extrapolated" (outside the measured range: the curves do not meet there; read off a power law
    fitted to the whole curve), "at most" (a time bounded by the curve's first point, already as
    low, where no power law falls back to it) or "not reached" (the curve never gets that low and
    does not fall, or falls so slowly that its power law would get there only beyond
    EXTRAPOLATION_LIMIT times its last time: no value)."""

    value: float
    how: str

    @property
    def measured(self) -> bool:
        return self.how in ("interpolated", "at most")


def _log_points(curve: Curve, metric: str = "smape") -> list[tuple[float, float]]:
    """(log seconds, log error) of the curve's points in spp order, error the CurvePoint field
    `metric` ("smape" or "relmse"), the unusable ones (≤ 0, not finite) left out."""
    values = [(p.seconds, getattr(p, metric)) for p in curve.points]
    return [(math.log(t), math.log(e)) for t, e in values if t > 0 and e > 0 and math.isfinite(e)]


def _power_law(points: list[tuple[float, float]]) -> tuple[float, float] | None:
    """(a, b) of log SMAPE = a + b · log seconds, least squares over every point (one noisy end
    segment of a timed curve is no basis for a guess); None unless the error falls with time."""
    if len(points) < 2 or len({x for x, _ in points}) < 2:
        return None
    b, a = np.polyfit([x for x, _ in points], [y for _, y in points], 1)
    return (float(a), float(b)) if b < 0 else None


def _between(y: float, y0: float, y1: float) -> bool:
    return min(y0, y1) <= y <= max(y0, y1)


def _line(x0: float, y0: float, x1: float, y1: float, y: float) -> float:
    return x1 if y1 == y0 else x0 + (y - y0) * (x1 - x0) / (y1 - y0)


def time_at_error(curve: Curve, target: float, metric: str = "smape") -> Reading:
    """Wall time at which `curve` reaches SMAPE `target`: log-log interpolation on the first segment
    (in spp order) whose errors bracket it; outside the curve's errors, the power law's time, unless
    that lies beyond EXTRAPOLATION_LIMIT times the curve's last time: a nearly flat curve (OIDN's
    bias on glass_shelf's glass) would claim ages, ~10⁹× its measured range, which is no estimate."""
    points = _log_points(curve, metric)
    if not points or not target > 0:
        return Reading(math.inf, "not reached")
    y = math.log(target)
    for (x0, y0), (x1, y1) in zip(points, points[1:]):
        if _between(y, y0, y1):
            return Reading(math.exp(_line(x0, y0, x1, y1, y)), "interpolated")
    if len(points) == 1 and points[0][1] == y:
        return Reading(math.exp(points[0][0]), "interpolated")
    fit = _power_law(points)
    if fit is None and y >= max(y for _, y in points):
        return Reading(math.exp(points[0][0]), "at most")  # already as low at its first point
    if fit is None:
        return Reading(math.inf, "not reached")
    log_seconds = (y - fit[0]) / fit[1]
    if log_seconds > math.log(EXTRAPOLATION_LIMIT) + max(x for x, _ in points):
        return Reading(math.inf, "not reached")
    return Reading(math.exp(log_seconds), "extrapolated")


def error_at_time(curve: Curve, seconds: float, metric: str = "smape") -> Reading:
    """SMAPE of `curve` at wall time `seconds`: log-log interpolation on the first segment (in spp
    order) whose times bracket it; outside the curve's times, the power law's SMAPE."""
    points = _log_points(curve, metric)
    if not points or not seconds > 0:
        return Reading(math.nan, "not reached")
    x = math.log(seconds)
    for (x0, y0), (x1, y1) in zip(points, points[1:]):
        if _between(x, x0, x1):
            return Reading(math.exp(_line(y0, x0, y1, x1, x)), "interpolated")
    fit = _power_law(points)
    return Reading(math.exp(fit[0] + fit[1] * x), "extrapolated") if fit else Reading(math.nan, "not reached")


@dataclass(frozen=True)
class Comparison:
    """The loop against one other method on one scene, at the loop's final error and time."""

    other: str  # the other curve's key
    target: float  # the loop's final error (SMAPE, or `metric`)
    loop_seconds: float  # the loop's wall time to it
    other_seconds: Reading  # the other method's wall time to the same error
    other_error: Reading  # the other method's error at the loop's wall time
    metric: str = "smape"  # the CurvePoint field the readings are in

    @property
    def speedup(self) -> float:
        """Equal-error speed-up: the other's time to the loop's final error ÷ the loop's time."""
        return self.other_seconds.value / self.loop_seconds

    @property
    def error_ratio(self) -> float:
        """Equal-time error ratio: the loop's error ÷ the other's at the loop's wall time (< 1: the loop ahead)."""
        return self.target / self.other_error.value


def compare(loop: Curve, other: Curve, metric: str = "smape") -> Comparison:
    """The loop's final point against `other`'s curve, both read in `metric` (a CurvePoint field)."""
    final = loop.points[-1]
    target = getattr(final, metric)
    return Comparison(other.key, target, final.seconds, time_at_error(other, target, metric),
                      error_at_time(other, final.seconds, metric), metric)


def better_of(loop: Curve, competitors: list[Curve], metric: str = "smape") -> Comparison:
    """The comparison against whichever competitor reaches the loop's final error sooner."""
    comparisons = [compare(loop, c, metric) for c in competitors]
    return min(comparisons, key=lambda c: c.other_seconds.value if math.isfinite(c.other_seconds.value) else math.inf)


@dataclass(frozen=True)
class EndReading:
    """The loop against one competitor at that competitor's last measured point (its highest spp):
    the competitor's side is a measurement, and the loop's time to the same error is read off the
    loop's own curve, "interpolated" between two of its points, "at most" its first point's time
    when that point is already as low (the speed-up is then a lower bound), else "extrapolated"."""

    other: str  # the competitor curve's key
    target: float  # the competitor's error at its last point
    other_seconds: float  # the competitor's time to its last point
    loop_seconds: Reading  # the loop's time to `target`

    @property
    def speedup(self) -> float:
        return self.other_seconds / self.loop_seconds.value

    @property
    def measured(self) -> bool:
        return self.loop_seconds.how in ("interpolated", "at most")


def at_competitor_end(loop: Curve, other: Curve, metric: str = "smape") -> EndReading:
    """The loop's time to `other`'s last error (see EndReading)."""
    end = other.points[-1]
    target = getattr(end, metric)
    first = next((p for p in loop.points if p.seconds > 0 and math.isfinite(getattr(p, metric))), None)
    if first is not None and getattr(first, metric) <= target:
        return EndReading(other.key, target, end.seconds, Reading(first.seconds, "at most"))
    return EndReading(other.key, target, end.seconds, time_at_error(loop, target, metric))


def least_at_competitor_ends(loop: Curve, competitors: list[Curve], metric: str = "smape") -> EndReading:
    """The reading least favourable to the loop among the competitors' last points: the strongest
    claim that needs no extrapolation of the competitor."""
    readings = [at_competitor_end(loop, c, metric) for c in competitors]
    return min(readings, key=lambda r: r.speedup if math.isfinite(r.speedup) else math.inf)
