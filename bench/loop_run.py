"""The loop benchmark's measurements: every method through the same `RenderLoop`, each
iteration scored against a cached high-spp reference, and the time-to-target headline.

    (a) uniform, no denoiser   (b) uniform + KPCN   (c) variance-adaptive + KPCN
    (d) error-predicted adaptive + KPCN (the product)   (e) uniform + OIDN (when pyoidn imports)
    (o) error-adaptive + KPCN allocating by the true error map (a bound on (d), not a product)

The machine is shared, so each loop runs `timing_repeats` times with identical seeds (identical
images) and each stage keeps its fastest repeat: the least disturbed measurement. A method's
cumulative time is therefore a sum of per-stage minimums, not one measured run.
"""
from __future__ import annotations

import itertools
import math
import statistics
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from bench.common import BenchNetworks, OidnDenoise, image_metrics, true_error_map
from bench.dev_references import DevScene, dev_scenes, scaled_film
from models.frames import FrameTensors
from models.pretrained import Networks
from service.dataset.procedural import generate_scene
from service.dataset.splits import scene_seeds
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec
from service.loop.tensors import to_image
from service.render.runtime import mitsuba

STAGES = ("render", "denoise", "error", "allocate")
HELDOUT_DATASET_SEED = 0  # scene_seeds("heldout", n, 0): never a training scene (service.dataset.splits)
LOOP_SEED = 0
# Below this mean predicted / true SMAPE the error network says "no error anywhere": (d) then
# allocates by numerical dust, and its headline measures nothing about error-driven sampling.
DEGENERATE_PREDICTION_RATIO = 0.05


# --- settings -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class BenchSettings:
    size: int | None  # square images (every method sees the same pixels); None: each scene's own film
    reference_spp: int
    iterations: int  # 16, 32, 64, … spp mean
    builtin_scenes: tuple[str, ...]
    heldout_scenes: int
    timing_repeats: int
    sampler: tuple[int, int, int]  # bench_sampler(size, spp, repeats)
    sampler_cases: int  # the first n of bench.sampler_report.CASES
    model_sizes: tuple[int, ...]
    model_repeats: int
    http_size: int
    http_requests: int
    suite: str = "procedural"  # "procedural": built-ins + held-out procedural; "dev": scenes/dev as written
    film_scale: int = 1  # dev suite: each film's width and height × this (2: about 512²)
    micro: bool = True  # the renderer / model / HTTP micro-benchmarks
    seed: int = LOOP_SEED  # LoopSpec.seed of every method's loop (--seeds runs one loop per seed)


FULL = BenchSettings(size=64, reference_spp=4096, iterations=5,
                     builtin_scenes=("cornell-box", "glossy-spheres", "fireflies"), heldout_scenes=2,
                     timing_repeats=3, sampler=(256, 64, 3), sampler_cases=3, model_sizes=(256, 512), model_repeats=3,
                     http_size=256, http_requests=40)
# The development suite (scenes/dev, never trained on) at its own film sizes (about 256²) against
# its committed references. Two timing repeats: with one, a scene's render stage alone moved by up
# to 20 % between two runs of the same loop on the shared host, enough to flip (d)-vs-(e) verdicts;
# two keep 12 scenes × 6 methods within about ten minutes.
DEV = BenchSettings(size=None, reference_spp=16384, iterations=4, builtin_scenes=(), heldout_scenes=0,
                    timing_repeats=2, sampler=(256, 64, 1), sampler_cases=0, model_sizes=(), model_repeats=0,
                    http_size=0, http_requests=0, suite="dev", micro=False)
QUICK = BenchSettings(size=32, reference_spp=512, iterations=3, builtin_scenes=("cornell-box",),
                      heldout_scenes=1, timing_repeats=1, sampler=(32, 16, 1), sampler_cases=1, model_sizes=(32,),
                      model_repeats=1, http_size=32, http_requests=6)


@dataclass(frozen=True)
class LoopMethod:
    key: str
    label: str
    allocator: str  # service.loop.spec.ALLOCATORS
    denoiser: str  # "none" | "kpcn" | "oidn"
    predicts_error: bool  # only the product pays for the error network
    oracle: bool = False  # allocates by the reference's true error map: a bound, not a product
    # > 0: allocates by the expected true error, from this many renders in lockstep
    # (bench.loop_expected_bound): the bound of any predictor of the scene's error
    replicas: int = 0


# (x)'s renders in lockstep: each allocates by the mean of the other three's true error maps.
EXPECTED_BOUND_REPLICAS = 4
METHODS: tuple[LoopMethod, ...] = (
    LoopMethod("a", "uniform, no denoiser", "uniform", "none", False),
    LoopMethod("b", "uniform + KPCN", "uniform", "kpcn", False),
    LoopMethod("c", "variance-adaptive + KPCN", "variance", "kpcn", False),
    LoopMethod("d", "error-predicted adaptive + KPCN", "error", "kpcn", True),
    LoopMethod("e", "uniform + OIDN", "uniform", "oidn", False),
    # What (d) would reach with a perfect error network: it separates "the predictor is not good
    # enough" from "error-driven allocation gains little on this scene".
    LoopMethod("o", "true-error adaptive + KPCN (bound: the reference's error map)", "error", "kpcn", False, oracle=True),
    # What a perfect predictor of the scene's expected error would reach: (o) also knows where
    # this render's noise landed, which no predictor can.
    LoopMethod("x", f"expected-error adaptive + KPCN (bound: the mean true error map of {EXPECTED_BOUND_REPLICAS - 1} "
               "other renders)", "error", "kpcn", False, replicas=EXPECTED_BOUND_REPLICAS),
)
# What `bench --loop` runs unless --methods names others: the replicated bound costs several loops.
DEFAULT_METHODS = tuple(m for m in METHODS if not m.replicas)
PRODUCT = "d"
# What the allocation bound needs (bench.loop_seeds): uniform + KPCN, the product, the true-error allocation.
BOUND_METHODS = ("b", "d", "o")


def select_methods(keys: list[str] | tuple[str, ...] | None) -> tuple[LoopMethod, ...]:
    """METHODS in their order, only `keys` when given; the headline is read against the product,
    so it is always among them."""
    if keys is None:
        return DEFAULT_METHODS
    known = {m.key for m in METHODS}
    unknown = sorted(set(keys) - known)
    if unknown:
        raise ValueError(f"unknown method(s) {', '.join(unknown)}: choose from {', '.join(sorted(known))}")
    if PRODUCT not in keys:
        raise ValueError(f"the methods must include the product ({PRODUCT}): every time is read against its SMAPE")
    return tuple(m for m in METHODS if m.key in keys)


@dataclass(frozen=True)
class BenchScene:
    label: str
    source: str  # a built-in name or an XML path: what LoopSpec.scene takes
    origin: str  # for the report
    dev: DevScene | None = None  # a development-suite scene: its reference is committed
    film: tuple[int, int] | None = None  # (width, height) the loop renders at; None: settings.size or the scene's own


# --- scenes and references ----------------------------------------------------------------------


def _export_bitmaps(description: dict, folder: Path, names: Iterator[int]) -> dict:
    """Copy of a scene dict with every in-memory `mi.Bitmap` written to an EXR beside the XML.

    Mitsuba's XML writer cannot serialise Bitmap objects (procedural textures and skies are
    generated in memory); float EXRs keep them linear, exactly as the in-memory bitmaps are.
    """
    mi = mitsuba()
    out: dict = {}
    for key, value in description.items():
        if isinstance(value, dict):
            out[key] = _export_bitmaps(value, folder, names)
        elif isinstance(value, mi.Bitmap):
            name = f"bitmap{next(names)}.exr"
            value.write(str(folder / name))
            out["filename"] = name  # a path relative to the XML: load_scene makes its folder the asset root
        else:
            out[key] = value
    return out


def procedural_scene_xml(seed: int, folder: Path, size: int) -> Path:
    """Held-out procedural scene `seed` as a Mitsuba XML file (+ its textures) in `folder`.

    RenderLoop takes names or XML paths, so the generator's dict goes through Mitsuba's own
    parser and writer (`mi.parser.write_file`) instead of a bench-only loop adapter.
    """
    mi = mitsuba()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "scene.xml"
    if path.is_file():
        return path
    description = _export_bitmaps(generate_scene(seed, size=size), folder, itertools.count())
    state = mi.parser.parse_dict(mi.parser.ParserConfig(mi.variant()), description)
    partial = folder / "scene.xml.partial"
    mi.parser.write_file(state, str(partial))
    partial.replace(path)  # a killed run never leaves a half-written scene behind
    return path


def prepare_scenes(settings: BenchSettings, cache_dir: Path, only: list[str] | None = None) -> list[BenchScene]:
    if settings.suite == "dev":
        return [BenchScene(scene.name, str(scene.path), "development suite", scene,
                           scaled_film(scene, settings.film_scale) if settings.film_scale > 1 else None)
                for scene in dev_scenes(only)]
    scenes = [BenchScene(name, name, "built-in") for name in settings.builtin_scenes]
    for seed in scene_seeds("heldout", settings.heldout_scenes, HELDOUT_DATASET_SEED):
        path = procedural_scene_xml(seed, cache_dir / "scenes" / f"heldout-{seed}", settings.size)
        scenes.append(BenchScene(f"heldout-{seed}", str(path), f"held-out procedural seed {seed}"))
    return scenes


class NoErrorPrediction(torch.nn.Module):
    """Stand-in error network for (b) and (c): they allocate without it, so they must not pay for
    it. The loop still stores an error map per iteration; zeros cost nothing."""

    change_scale: float | None = None   # models.error_predictor.ErrorMap: no calibration,
    reads_disagreement = False          # no disagreement input

    def forward(self, frame: FrameTensors, denoised: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(denoised[:, :1])


# An extrapolated time more than this many times the curve's last time is no estimate: a
# nearly flat last segment (an untrained network's loop) would claim ages.
EXTRAPOLATION_LIMIT = 100.0


def time_to_reach(seconds: list[float], errors: list[float], target: float) -> tuple[float, str]:
    """Wall time at which the error curve reaches `target`, interpolated linearly in log-log.

    Returns (seconds, how): "interpolated"; "first iteration" (already reached by the first
    point: the time is an upper bound); "extrapolated" (never reached: the last segment's
    log-log slope continued, a guess flagged as such); "not reached" (inf: the curve stopped
    falling, or would reach it only beyond EXTRAPOLATION_LIMIT times its last time).
    """
    pairs = [(t, e) for t, e in zip(seconds, errors) if t > 0 and e > 0 and math.isfinite(e)]
    if not pairs or not target > 0:
        return math.inf, "not reached"
    if pairs[0][1] <= target:
        return pairs[0][0], "first iteration"
    for (t0, e0), (t1, e1) in zip(pairs, pairs[1:]):
        if e1 <= target:
            return _loglog_at(t0, e0, t1, e1, target), "interpolated"
    if len(pairs) >= 2 and pairs[-1][1] < pairs[-2][1]:
        (t0, e0), (t1, e1) = pairs[-2], pairs[-1]
        guess = _loglog_at(t0, e0, t1, e1, target)
        if guess <= EXTRAPOLATION_LIMIT * t1:
            return guess, "extrapolated"
    return math.inf, "not reached"


def _loglog_at(t0: float, e0: float, t1: float, e1: float, target: float) -> float:
    if e1 == e0:
        return t1
    u = (math.log(target) - math.log(e0)) / (math.log(e1) - math.log(e0))
    log_time = math.log(t0) + u * (math.log(t1) - math.log(t0))
    # a nearly flat segment sends the guess past any float (exp overflows): no time at all
    return math.exp(log_time) if log_time < math.log(sys.float_info.max) else math.inf


# --- running one method on one scene -------------------------------------------------------------


@dataclass
class Row:
    """One iteration of one method on one scene: a CSV line."""

    scene: str
    method: str
    iteration: int
    spp_mean: float
    stage_seconds: dict[str, float]
    cumulative_seconds: float
    metrics: dict[str, float]
    predicted_error: float | None


@dataclass
class MethodRun:
    method: LoopMethod
    rows: list[Row]
    image: np.ndarray  # final denoised (or noisy) image
    spp_map: np.ndarray
    predicted_error: np.ndarray | None  # final predicted SMAPE map, (d) only


def loop_spec(scene: BenchScene, method: LoopMethod, settings: BenchSettings, iterations: int) -> LoopSpec:
    width, height = scene.film or (settings.size, settings.size)
    return LoopSpec(scene=scene.source, width=width, height=height, max_iterations=iterations,
                    allocator=method.allocator, denoise=method.denoiser == "kpcn", seed=settings.seed)


class TrueErrorMap(torch.nn.Module):
    """Stand-in error network for (o): the denoised image's true per-pixel SMAPE against the
    reference, what a perfect error network would predict."""

    change_scale: float | None = None   # models.error_predictor.ErrorMap: the true error needs no
    reads_disagreement = False          # calibration and reads no disagreement

    def __init__(self, reference: np.ndarray):
        super().__init__()
        self.reference = reference

    def forward(self, frame: FrameTensors, denoised: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(true_error_map(to_image(denoised), self.reference))[None, None]


def _make_loop(scene: BenchScene, method: LoopMethod, settings: BenchSettings, nets: BenchNetworks,
               iterations: int, reference: np.ndarray | None = None) -> RenderLoop:
    if method.oracle:
        if reference is None:
            raise ValueError(f"method ({method.key}) allocates by the true error: it needs the reference")
        error_predictor = TrueErrorMap(reference)
    else:
        error_predictor = nets.networks.error_predictor if method.predicts_error else NoErrorPrediction()
    return RenderLoop(loop_spec(scene, method, settings, iterations), Networks(nets.networks.denoiser, error_predictor))


def warm_up(scene: BenchScene, settings: BenchSettings, nets: BenchNetworks) -> None:
    """One untimed iteration of the product per scene: Dr.Jit compiles the scene's kernels and
    oneDNN builds its primitives for this size once, instead of inside whichever method runs first."""
    product = next(m for m in METHODS if m.key == PRODUCT)
    for _ in _make_loop(scene, product, settings, nets, iterations=1).run():
        pass


def run_method(scene: BenchScene, method: LoopMethod, settings: BenchSettings, nets: BenchNetworks,
               reference: np.ndarray, oidn: OidnDenoise | None = None) -> MethodRun:
    repeats: list[list[dict[str, float]]] = []
    first: list[tuple] = []  # (record summary, image) of the first repeat; all repeats are identical
    final = None
    for repeat in range(settings.timing_repeats):
        timings = []
        for record in _make_loop(scene, method, settings, nets, settings.iterations, reference).run():
            stage = {name: float(record.timings.get(name, 0.0)) for name in STAGES}
            image = record.denoised[0]
            if method.denoiser == "oidn":
                t0 = time.perf_counter()
                buffer = record.buffers[0]
                image = oidn(buffer.mean, buffer.albedo, buffer.normal)
                stage["denoise"] = time.perf_counter() - t0
            timings.append(stage)
            if repeat == 0:
                predicted = record.error[0] if method.predicts_error else None
                first.append((record.iteration, record.spp_mean, image,
                              None if predicted is None else float(np.mean(predicted))))
                final = (image, record.buffers[0].spp.copy(), None if predicted is None else predicted.copy())
        repeats.append(timings)
    rows, cumulative = [], 0.0
    for i, (iteration, spp_mean, image, predicted_mean) in enumerate(first):
        # Fastest repeat per stage: identical work each time, so the minimum is the run least
        # disturbed by the other jobs on the machine.
        stage = {name: min(r[i][name] for r in repeats) for name in STAGES}
        cumulative += sum(stage.values())
        rows.append(Row(scene.label, method.key, iteration, spp_mean, stage, cumulative,
                        image_metrics(image, reference), predicted_mean))
    image, spp_map, predicted = final
    return MethodRun(method, rows, image, spp_map, predicted)


# --- headline -----------------------------------------------------------------------------------


@dataclass
class SceneResult:
    scene: BenchScene
    reference: np.ndarray
    runs: dict[str, MethodRun]


@dataclass
class Headline:
    target: dict[str, float]  # per scene: the SMAPE (d) reaches at its last iteration
    times: dict[str, dict[str, tuple[float, str]]]  # scene → method → (seconds, how)
    speedup: dict[str, dict[str, float]]  # scene → method → t_method / t_d
    median_speedup: dict[str, float]
    smape_ratio: dict[str, float]  # scene → SMAPE(d) / SMAPE(b) at the last iteration
    median_smape_ratio: float
    oracle_ratio: dict[str, float] = field(default_factory=dict)  # scene → SMAPE(o) / SMAPE(b), same samples
    median_oracle_ratio: float = math.nan
    expected_ratio: dict[str, float] = field(default_factory=dict)  # scene → SMAPE(x) / SMAPE(b), same samples


def headline(results: list[SceneResult]) -> Headline:
    target, times, speedup, ratio, oracle, expected = {}, {}, {}, {}, {}, {}
    for result in results:
        label, runs = result.scene.label, result.runs
        product = runs[PRODUCT].rows
        target[label] = product[-1].metrics["smape"]
        times[label] = {}
        for key, run in runs.items():
            seconds = [r.cumulative_seconds for r in run.rows]
            times[label][key] = time_to_reach(seconds, [r.metrics["smape"] for r in run.rows], target[label])
        t_product = times[label][PRODUCT][0]
        speedup[label] = {key: t / t_product for key, (t, _) in times[label].items() if key != PRODUCT}
        if "b" in runs:
            ratio[label] = product[-1].metrics["smape"] / runs["b"].rows[-1].metrics["smape"]
            if "o" in runs:
                oracle[label] = runs["o"].rows[-1].metrics["smape"] / runs["b"].rows[-1].metrics["smape"]
            if "x" in runs:
                expected[label] = runs["x"].rows[-1].metrics["smape"] / runs["b"].rows[-1].metrics["smape"]
    keys = sorted({k for s in speedup.values() for k in s})
    median_speedup = {k: statistics.median(s[k] for s in speedup.values() if k in s) for k in keys}
    return Headline(target, times, speedup, median_speedup, ratio,
                    statistics.median(ratio.values()) if ratio else math.nan,
                    oracle, statistics.median(oracle.values()) if oracle else math.nan, expected)


# --- what the last iteration says about the samples and the error map ----------------------------


def convergence_exponent(run: MethodRun) -> float:
    """k in SMAPE ∝ spp^k over the run (least squares in log-log). Plain Monte Carlo gives about
    −0.5; a much shallower (a) means fireflies dominate, or the reference itself is noisy."""
    spp = np.log([r.spp_mean for r in run.rows])
    err = np.log([max(r.metrics["smape"], 1e-12) for r in run.rows])
    return float(np.polyfit(spp, err, 1)[0]) if len(spp) > 1 else math.nan


def mean_ratio(predicted: np.ndarray, true: np.ndarray) -> float:
    return float(predicted.mean() / max(float(true.mean()), 1e-12))


def log_correlation(predicted: np.ndarray, true: np.ndarray) -> float:
    """Pearson correlation of log predicted vs log true per-pixel SMAPE."""
    p, t = np.log(np.maximum(predicted.ravel(), 1e-6)), np.log(np.maximum(true.ravel(), 1e-6))
    with np.errstate(invalid="ignore", divide="ignore"):  # a flat map has no correlation: nan
        return float(np.corrcoef(p, t)[0, 1])


@dataclass(frozen=True)
class ErrorAgreement:
    """(d)'s last iteration on one scene: where the samples went and how good the error map was."""

    scene: str
    spp_min: int
    spp_median: float
    spp_max: int
    correlation: float  # log predicted vs log true per-pixel SMAPE
    ratio: float  # mean predicted / mean true SMAPE
    exponent: float  # convergence exponent of (a)


def error_agreement(result: SceneResult) -> ErrorAgreement:
    d = result.runs[PRODUCT]
    true = true_error_map(d.image, result.reference)
    predicted = d.predicted_error if d.predicted_error is not None else np.zeros_like(true)
    exponent = convergence_exponent(result.runs["a"]) if "a" in result.runs else math.nan
    return ErrorAgreement(result.scene.label, int(d.spp_map.min()), float(np.median(d.spp_map)), int(d.spp_map.max()),
                          log_correlation(predicted, true), mean_ratio(predicted, true), exponent)
