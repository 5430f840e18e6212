"""The quality report's evaluation: the images (held-out split of a data set, built-in scenes
rendered here), every method on every image, and the tables the report prints.

The methods are the ONE trained network with stages switched off (ablations, not separately
trained networks), plus Intel Open Image Denoise through bench.common's one call.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from torch import Tensor

from bench.common import oidn_denoiser, sanitize as clean, scene_reference, score
from bench.quality_measures import flicker, lambda_measures, nanstats, pearson, spearman
from models.denoiser import Denoiser, DenoiserCache
from models.pyramid import down, pad_to
from models.error_predictor import ErrorPredictor
from models.features import demodulate
from models.frames import FrameTensors
from models.losses import SMAPE_EPS, smape, smape_map
from models.pretrained import Networks
from service.dataset.build import read_manifest
from service.dataset.loader import DenoiserDataset
from service.exr import read_exr
from service.loop.denoise_frame import denoise_and_predict, denoise_frame
from service.loop.tensors import frame_tensors, nchw, to_image
from service.render.effects import inspect_scene, make_integrator
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.scenes import load_scene

# Uniform input levels of the data set (service.dataset.build.UNIFORM_STEPS) and the matching
# progressive passes for built-in scenes: (total spp after the pass, samples added).
LEVELS = ("spp16", "spp32", "spp64", "spp128")
PROGRESSIVE_STEPS = ((16, 16), (32, 16), (64, 32), (128, 64))
HEADLINE_SPP = 16
LAMBDAS = (1.0, 2.0, 5.0, 10.0)

NOISY, SINGLE, MULTISCALE, OIDN = ("noisy input", "single-scale (1 frame)", "multi-scale (1 frame)", "OIDN (pyoidn)")
# The row the loop runs on a sequence's window, named after what the weights do with it: a
# temporal network filters the warped window jointly (one kernel per frame, one softmax); a
# single-frame network (the shipped one) denoises the centre frame with its neighbours'
# consistent samples pooled in (models/accumulation.py).
TEMPORAL, POOLED = "temporal multi-scale", "pooled window"

# Built-in scenes are static: a "sequence" is the same view rendered with different seeds,
# which is exactly what the loop renders for `--frames F` of a static scene.
SEQUENCE_SEEDS = (11, 12, 13)
FLICKER_SEEDS = (101, 102, 103, 104, 105)
FLICKER_SPP = 16


def log(message: str) -> None:
    print(f"[quality {time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


# --- what is evaluated ---------------------------------------------------------------------------

@dataclass
class EvalImage:
    """One image to denoise: a window of noisy frames (each (1,C,H,W)) and the centre's reference."""

    group: str                 # "held-out" or "built-in"
    scene: str
    spp: int
    window: list[FrameTensors]
    centre: int
    reference: Tensor          # (1,3,H,W) linear HDR

    @property
    def frame(self) -> FrameTensors:
        return self.window[self.centre]


@dataclass
class Outputs:
    """Every method's result for one image, plus the error prediction of the loop's result."""

    image: EvalImage
    results: dict[str, Tensor]               # method → (1,3,H,W)
    window: str                              # the method the loop runs (window_method)
    predicted_error: Tensor | None = None    # (1,1,H,W), for the loop's result
    lambda_results: dict[float, Tensor] = field(default_factory=dict)
    pyramid: list[dict[str, float]] = field(default_factory=list)   # per coarse level, see pyramid_levels

    @property
    def loop_result(self) -> Tensor:
        """What the loop hands on for this image: the window method's result."""
        return self.results[self.window]


Denoise = Callable[[EvalImage], Tensor]


# --- the networks --------------------------------------------------------------------------------

def ablation(trained: Denoiser, **switches: bool) -> Denoiser:
    """The trained network with some of its stages switched off (e.g. multiscale=False).

    Weights of modules the smaller config does not build (compositor, temporal extractor) are
    dropped; every module it does build must find its weights, else this is not the same net.
    """
    config = dataclasses.replace(trained.config, **switches)
    model = Denoiser(config)
    missing, _unused = model.load_state_dict(trained.state_dict(), strict=False)
    if missing:
        raise RuntimeError(f"ablation {switches} needs weights the trained denoiser lacks: {missing}")
    return model.eval()


def oidn_method() -> tuple[Denoise, str]:
    """OIDN (the service's one call) on the centre frame's noisy colour, albedo and normal."""
    denoise, note = oidn_denoiser()

    def run(image: EvalImage) -> Tensor:
        f = image.frame
        return nchw(denoise(to_image(f.color), to_image(f.albedo), to_image(f.normal)))

    return run, note


def window_method(denoiser: Denoiser) -> str:
    """The name of the row the loop runs on a window, after what these weights do with it."""
    return TEMPORAL if denoiser.temporal is not None else POOLED


def windowed(denoiser: Denoiser, image: EvalImage) -> Tensor:
    """The denoiser over the image's whole window, as the loop runs a sequence (λ = 1)."""
    window, centre = denoiser.filtered_window(image.window, image.centre)
    return denoise_frame(denoiser, window, centre)


def make_methods(denoiser: Denoiser, use_oidn: bool) -> tuple[dict[str, Denoise], str | None]:
    """Denoise name → function of an EvalImage, in table order; and the OIDN note."""
    single = ablation(denoiser, multiscale=False, temporal=False)
    methods: dict[str, Denoise] = {
        NOISY: lambda im: im.frame.color,
        SINGLE: lambda im: denoise_frame(single, [im.frame], 0),
        MULTISCALE: lambda im: denoise_frame(denoiser, [im.frame], 0),
        window_method(denoiser): lambda im: windowed(denoiser, im),
    }
    note = None
    if use_oidn:
        methods[OIDN], note = oidn_method()
    else:
        note = "OIDN was not run (switched off for this run)."
    return methods, note


# --- inputs: the held-out split ------------------------------------------------------------------

def heldout_images(data_dir: Path, radius: int) -> tuple[list[EvalImage], dict]:
    """Every full window of the held-out split at each uniform level; and the split's manifest entry."""

    entry = read_manifest(data_dir)["splits"].get("heldout")
    if entry is None:
        # FileNotFoundError: the CLI reports it as a user error (one line, no traceback).
        raise FileNotFoundError(f"{data_dir} has no held-out split; build it with "
                                f"`renderloop dataset -o {data_dir} --split heldout ...`")
    radius = min(radius, (entry["frames"] - 1) // 2)  # shorter sequences: the widest window that fits
    dataset = DenoiserDataset(data_dir, split="heldout", radius=radius, crop=None, levels=LEVELS)
    images = []
    references: set[Path] = set()
    for index, item in enumerate(dataset.items):
        sample = dataset[index]
        steps = sample.noisy.color.shape[0]
        window = [sample.noisy.map(lambda _, t, i=i: t[i:i + 1]) for i in range(steps)]
        images.append(EvalImage("held-out", f"scene_{item.scene}/frame_{item.frames[sample.centre]}",
                                int(item.level.removeprefix("spp")), window, sample.centre,
                                sample.reference[sample.centre][None]))
        references.add(item.references[sample.centre])
    return images, {**entry, "radius": radius, "reference_noise": reference_noise(sorted(references))}


def reference_noise(paths: Sequence[Path]) -> float:
    """Mean relative standard error of the references' pixels (same ε as SMAPE): the exact image
    scores about 0.4× this in SMAPE against them, so it bounds what the scores resolve."""

    values = []
    for path in paths:
        frame = read_exr(path)
        if frame.variance is not None:
            values.append(float(np.mean(np.sqrt(np.maximum(frame.variance, 0)) / (np.abs(frame.color) + SMAPE_EPS))))
    return float(np.mean(values)) if values else float("nan")


# --- inputs: built-in scenes rendered here -------------------------------------------------------

@dataclass
class BuiltinRenderer:
    """Renders a built-in scene the way the loop does (same integrator choice, film size)."""

    name: str
    size: int

    def __post_init__(self) -> None:
        self.scene = load_scene(self.name, width=self.size, height=self.size)
        self.integrator = make_integrator(inspect_scene(self.name, width=self.size, height=self.size))

    def render(self, buffer: FrameBuffer, spp: int, seed: int) -> None:
        render_samples(self.scene, np.full((self.size, self.size), spp), buffer, integrator=self.integrator, seed=seed)

    def fresh(self) -> FrameBuffer:
        return FrameBuffer.empty(self.size, self.size)


def builtin_reference(renderer: BuiltinRenderer, spp: int, cache_dir: Path) -> tuple[Tensor, float]:
    """The high-spp reference (bench.common's renders and cache) and its own noise level."""
    log(f"reference of {renderer.name} at {renderer.size}², {spp} spp (cached in {cache_dir})")
    reference = scene_reference(renderer.name, renderer.name, renderer.size, spp, cache_dir)
    return nchw(reference.mean), reference.relative_error


def builtin_images(renderer: BuiltinRenderer, reference: Tensor) -> list[EvalImage]:
    """Three seeds of the static view, accumulated 16 → 32 → 64 → 128 spp; the middle one is 'the' frame."""

    buffers = [renderer.fresh() for _ in SEQUENCE_SEEDS]
    images = []
    for total, added in PROGRESSIVE_STEPS:
        for buffer, seed in zip(buffers, SEQUENCE_SEEDS):
            renderer.render(buffer, added, seed)
        window = [frame_tensors(b) for b in buffers]
        images.append(EvalImage("built-in", renderer.name, total, window, len(window) // 2, reference))
    return images




# --- evaluation ----------------------------------------------------------------------------------

def evaluate(images: list[EvalImage], methods: dict[str, Denoise], denoiser: Denoiser,
             predictor: ErrorPredictor, lambdas: Sequence[float]) -> list[Outputs]:
    """Run every method on every image; at the headline level also the λ sweep (one prepare,
    several cheap λ tails, as the service does)."""
    outputs, window_name = [], window_method(denoiser)
    for n, image in enumerate(images, 1):
        window, centre = denoiser.filtered_window(image.window, image.centre)
        # one prepare gives the loop's result (what `windowed` computes), the error network's map
        # of it and the cache of the λ sweep
        result = denoise_and_predict(Networks(denoiser, predictor), window, centre)
        cache, denoised, predicted = result.cache, result.image, result.error
        results = {name: denoised if name == window_name else method(image) for name, method in methods.items()}
        out = Outputs(image, results, window_name, predicted_error=predicted)
        if image.spp == HEADLINE_SPP:
            out.lambda_results = {lam: denoiser.apply(cache, lam) for lam in lambdas}
            out.pyramid = pyramid_levels(denoiser, cache, image)
        outputs.append(out)
        if n % 8 == 0 or n == len(images):
            log(f"{image.group}: {n}/{len(images)} images denoised")
    return outputs


def pyramid_levels(denoiser: Denoiser, cache: DenoiserCache, image: EvalImage) -> list[dict[str, float]]:
    """Per coarse level l (λ = 1, demodulated, against the reference pooled l times): SMAPE of the
    level's own result, of the finest result pooled l times, of the noisy input pooled l times;
    and the compositor's mean α where the level's result enters the next finer one.

    A coarse level helps only where its own result beats the pooled finest one; when it is no
    better than the pooled noisy input it was never trained, and α goes to 0 (the failure the
    coarse-level loss in models/training.py fixed)."""
    if denoiser.composite is None:
        return []
    levels, alphas = denoiser.filter_levels(cache, 1.0), []
    denoiser.merge_levels(cache, levels, alphas)
    alphas.reverse()                                   # finest step first: alphas[l-1] joins level l
    align = denoiser.config.alignment
    reference = demodulate(pad_to(clean(image.reference), align), cache.albedo)
    noisy = demodulate(pad_to(clean(image.frame.color), align), cache.albedo)
    finest, rows = levels[0], []
    for level, alpha in zip(levels[1:], alphas):
        reference, noisy, finest = down(reference), down(noisy), down(finest)
        rows.append({"own": float(smape(level, reference)), "pooled_finest": float(smape(finest, reference)),
                     "pooled_noisy": float(smape(noisy, reference)), "alpha": float(alpha.mean())})
    return rows


def quality_table(outputs: list[Outputs], methods: Sequence[str]) -> dict[tuple[int, str], dict[str, float]]:
    """(spp, method) → mean of each per-image metric."""
    rows: dict[tuple[int, str], list[dict[str, float]]] = {}
    for out in outputs:
        for name in methods:
            rows.setdefault((out.image.spp, name), []).append(score(out.results[name], out.image.reference))
    return {key: {m: float(np.mean([s[m] for s in scores])) for m in scores[0]} for key, scores in rows.items()}


def headline_factor(table: dict[tuple[int, str], dict[str, float]], window: str) -> float:
    """Mean SMAPE of the noisy input ÷ of the loop's result (`window`) at the headline level."""
    noisy, best = table.get((HEADLINE_SPP, NOISY)), table.get((HEADLINE_SPP, window))
    return noisy["smape"] / best["smape"] if noisy and best and best["smape"] > 0 else float("nan")


def per_scene_headline(outputs: list[Outputs]) -> list[tuple[str, float, float]]:
    """(scene, SMAPE noisy, SMAPE of the loop's result) at the headline level, per image."""
    return [(o.image.scene, float(smape(clean(o.results[NOISY]), o.image.reference)),
             float(smape(clean(o.loop_result), o.image.reference)))
            for o in outputs if o.image.spp == HEADLINE_SPP]


def lambda_table(outputs: list[Outputs]) -> dict[float, dict[str, float]]:
    per_lambda: dict[float, list[dict[str, float]]] = {}
    for out in outputs:
        for lam, result in out.lambda_results.items():
            per_lambda.setdefault(lam, []).append(lambda_measures(result, out.image.reference))
    return {lam: {m: nanstats(s[m] for s in rows)[0] for m in rows[0]} for lam, rows in sorted(per_lambda.items())}


def error_predictor_table(outputs: list[Outputs]) -> dict[int, dict[str, tuple]]:
    """spp → Pearson/Spearman stats per image and mean predicted vs true SMAPE."""
    rows: dict[int, list[tuple[float, float, float, float]]] = {}
    for out in outputs:
        true = smape_map(clean(out.loop_result), out.image.reference).numpy()
        pred = out.predicted_error.numpy()
        rows.setdefault(out.image.spp, []).append(
            (pearson(pred, true), spearman(pred, true), float(pred.mean()), float(true.mean())))
    return {spp: {"pearson": nanstats(r[0] for r in rs), "spearman": nanstats(r[1] for r in rs),
                  "predicted": nanstats(r[2] for r in rs), "true": nanstats(r[3] for r in rs), "n": len(rs)}
            for spp, rs in sorted(rows.items())}


def flicker_rows(renderer: BuiltinRenderer, reference: Tensor, methods: dict[str, Denoise]) -> dict[str, tuple[float, float]]:
    """Static view, FLICKER_SEEDS renders at FLICKER_SPP; every frame with a full window is denoised
    (its window: the previous, itself, the next) and consecutive results are compared."""

    frames = []
    for seed in FLICKER_SEEDS:
        buffer = renderer.fresh()
        renderer.render(buffer, FLICKER_SPP, seed)
        frames.append(frame_tensors(buffer))
    mean_ref = float(clean(reference).mean()) or 1.0
    rows = {}
    for name, method in methods.items():
        results = [method(EvalImage("flicker", renderer.name, FLICKER_SPP, frames[t - 1:t + 2], 1, reference))
                   for t in range(1, len(frames) - 1)]
        linear, shown = flicker(results)
        rows[name] = (linear / mean_ref, shown)
    return rows




def pick_example(outputs: list[Outputs], prefer: str | None = None) -> Outputs | None:
    """At the headline level: the preferred scene if present, else the image whose loop result
    has the median SMAPE (a representative image, not the best one)."""
    candidates = [o for o in outputs if o.image.spp == HEADLINE_SPP]
    if not candidates:
        return None
    for o in candidates:
        if o.image.scene == prefer:
            return o
    ranked = sorted(candidates, key=lambda o: float(smape(clean(o.loop_result), o.image.reference)))
    return ranked[len(ranked) // 2]

