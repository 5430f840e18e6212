"""`renderloop bench --denoiser --data DIR`: the denoiser quality report, docs/denoiser.md.

What it measures, on the held-out split of a built data set and on built-in scenes rendered
here, at 16/32/64/128 spp:

- SMAPE, relMSE (linear HDR), PSNR and 1−SSIM (clamped sRGB) for the noisy input and three
  configurations of the ONE trained network: single-frame KPCN (finest level, no compositing),
  multi-scale on one frame, and temporal multi-scale on a 2M+1 window — plus Intel Open Image
  Denoise when `pyoidn` imports;
- temporal flicker on static scenes re-rendered with different seeds;
- residual noise and kept detail as λ goes from 1 to 10;
- how well the error predictor ranks pixels (Pearson and Spearman per image);
- a few PNG crops.

The ablations reuse the trained weights in a config with the feature switched off (modules
that the smaller config does not build are simply not loaded); they are not separately trained
networks, and the report says so.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from bench.common import (REFERENCE_SEED, cached_reference, display, oidn_denoiser, pinned_torch_threads,
                          provenance, sanitize as clean, score)
from models.checkpoint import load_checkpoint
from models.denoiser import Denoiser, DenoiserCache, down, pad_to
from models.features import demodulate
from models.error_predictor import ErrorPredictor
from models.frames import FrameTensors
from models.losses import SMAPE_EPS, smape, smape_map
from models.pretrained import SHIPPED_WEIGHTS_DIR, DENOISER_FILE, ERROR_PREDICTOR_FILE
from service.dataset.build import read_manifest
from service.dataset.loader import DenoiserDataset
from service.exr import read_exr
from service.images import false_colour, tonemap, write_png
from service.loop.tensors import frame_tensors, nchw, to_image
from service.render.effects import inspect_scene, make_integrator
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.runtime import active_variant
from service.render.scenes import load_scene

REPORT_COMMAND = "renderloop bench --denoiser --data {data}"
REPORT_NAME = "denoiser.md"
CROPS_DIR = "denoiser"  # PNGs next to the report, linked relatively

# Uniform input levels of the data set (service.dataset.build.UNIFORM_STEPS) and the matching
# progressive passes for built-in scenes: (total spp after the pass, samples added).
LEVELS = ("spp16", "spp32", "spp64", "spp128")
PROGRESSIVE_STEPS = ((16, 16), (32, 16), (64, 32), (128, 64))
HEADLINE_SPP = 16
LAMBDAS = (1.0, 2.0, 5.0, 10.0)

NOISY, SINGLE, MULTISCALE, TEMPORAL, OIDN = (
    "noisy input", "single-frame KPCN", "multi-scale (1 frame)", "temporal multi-scale", "OIDN (pyoidn)")

# Built-in scenes are static: a "sequence" is the same view rendered with different seeds,
# which is exactly what the loop renders for `--frames F` of a static scene.
SEQUENCE_SEEDS = (11, 12, 13)
FLICKER_SEEDS = (101, 102, 103, 104, 105)
FLICKER_SPP = 16

REC709_LUMA = (0.2126, 0.7152, 0.0722)  # ITU-R BT.709 luminance weights
FLAT_QUANTILE = 0.5    # pixels whose reference gradient is in the lower half count as "flat"
DETAIL_QUANTILE = 0.75  # the top quarter of reference gradients counts as "detail"
CROP_SIDE = 64         # crops are at most this many pixels a side...
CROP_DISPLAY = 128     # ...and upscaled (nearest) to about this many for viewing


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
    """Every method's result for one image, plus the temporal model's error prediction."""

    image: EvalImage
    results: dict[str, Tensor]               # method → (1,3,H,W)
    predicted_error: Tensor | None = None    # (1,1,H,W), for the temporal result
    lambda_results: dict[float, Tensor] = field(default_factory=dict)
    pyramid: list[dict[str, float]] = field(default_factory=list)   # per coarse level, see pyramid_levels


Method = Callable[[EvalImage], Tensor]


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


def oidn_method() -> tuple[Method | None, str]:
    """OIDN (bench.common's one call) on the centre frame's noisy colour, albedo and normal."""
    denoise, note = oidn_denoiser()
    if denoise is None:
        return None, note

    def run(image: EvalImage) -> Tensor:
        f = image.frame
        return nchw(denoise(to_image(f.color), to_image(f.albedo), to_image(f.normal)))

    return run, note


def make_methods(denoiser: Denoiser, use_oidn: bool) -> tuple[dict[str, Method], str | None]:
    """Method name → function of an EvalImage, in table order; and the OIDN note."""
    single = ablation(denoiser, multiscale=False, temporal=False)
    methods: dict[str, Method] = {
        NOISY: lambda im: im.frame.color,
        SINGLE: lambda im: single([im.frame], 0, 1.0),
        MULTISCALE: lambda im: denoiser([im.frame], 0, 1.0),
        TEMPORAL: lambda im: denoiser(im.window, im.centre, 1.0),
    }
    note = None
    if use_oidn:
        run, note = oidn_method()
        if run is not None:
            methods[OIDN] = run
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

    def render(self, buffer, spp: int, seed: int) -> None:

        render_samples(self.scene, np.full((self.size, self.size), spp), buffer, integrator=self.integrator, seed=seed)

    def fresh(self):

        return FrameBuffer.empty(self.size, self.size)


def builtin_reference(renderer: BuiltinRenderer, spp: int, cache_dir: Path) -> tuple[Tensor, float]:
    """The high-spp reference (bench.common's cache) and its own noise level."""
    path = cache_dir / f"{renderer.name}_{renderer.size}px_{spp}spp_{active_variant()}_seed{REFERENCE_SEED}.npz"

    def render(seed: int) -> tuple[np.ndarray, np.ndarray]:
        log(f"rendering the {spp}-spp reference of {renderer.name} at {renderer.size}² (cached in {cache_dir})")
        buffer = renderer.fresh()
        renderer.render(buffer, spp, seed)
        return buffer.mean, buffer.variance

    reference = cached_reference(path, render)
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


# --- metrics -------------------------------------------------------------------------------------

def log_luminance(t: Tensor) -> Tensor:
    """(1,3,H,W) → (1,1,H,W) log(1 + Rec.709 luminance): a scale-tolerant axis for detail measures."""
    w = torch.tensor(REC709_LUMA, dtype=torch.float32).view(1, 3, 1, 1)
    return torch.log1p((clean(t) * w).sum(1, keepdim=True))


def high_pass(x: Tensor) -> Tensor:
    """x − 3×3 box blur (replicate borders): the pixel-scale band where noise and fine detail live."""
    return x - F.avg_pool2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3, stride=1)


def gradient_magnitude(x: Tensor) -> Tensor:
    """Central-difference gradient magnitude (replicate borders)."""
    p = F.pad(x, (1, 1, 1, 1), mode="replicate")
    dx = (p[..., 1:-1, 2:] - p[..., 1:-1, :-2]) / 2
    dy = (p[..., 2:, 1:-1] - p[..., :-2, 1:-1]) / 2
    return torch.sqrt(dx * dx + dy * dy)


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.ravel().astype(np.float64), b.ravel().astype(np.float64)
    a, b = a - a.mean(), b - b.mean()
    denom = math.sqrt(float((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / denom) if denom > 0 else float("nan")


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Rank correlation; scipy's (average ranks for ties) when installed, else plain numpy ranks."""
    try:
        from scipy.stats import spearmanr
    except ImportError:
        return pearson(np.argsort(np.argsort(a.ravel())), np.argsort(np.argsort(b.ravel())))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a constant input: nan is the honest answer
        return float(spearmanr(a.ravel(), b.ravel())[0])


def lambda_measures(d: Tensor, r: Tensor) -> dict[str, float]:
    """Residual noise and kept detail of a result d against the reference r (see the report text)."""
    ld, lr = log_luminance(d), log_luminance(r)
    grad_r = gradient_magnitude(lr)
    flat = grad_r <= torch.quantile(grad_r, FLAT_QUANTILE)
    detail = grad_r >= torch.quantile(grad_r, DETAIL_QUANTILE)
    hd, hr = high_pass(ld), high_pass(lr)
    noise = float((hd - hr).abs()[flat].mean())
    ref_energy = float(hr.abs()[detail].mean())
    ratio = float(hd.abs()[detail].mean()) / ref_energy if ref_energy > 0 else float("nan")
    return {"smape": float(smape(clean(d), clean(r))), "noise": noise, "detail": ratio,
            "grad_corr": pearson(gradient_magnitude(ld).numpy(), grad_r.numpy())}


def flicker(frames: Sequence[Tensor]) -> tuple[float, float]:
    """Mean |consecutive difference|: in linear radiance, and in sRGB 0–255 units."""
    linear = [float((clean(b) - clean(a)).abs().mean()) for a, b in zip(frames, frames[1:])]
    shown = [float((display(clean(b)) - display(clean(a))).abs().mean()) * 255 for a, b in zip(frames, frames[1:])]
    return float(np.mean(linear)), float(np.mean(shown))


def nanstats(values: Iterable[float]) -> tuple[float, float, float, int]:
    """(mean, min, max, n) over the finite values."""
    v = np.array([x for x in values if np.isfinite(x)], dtype=np.float64)
    if not v.size:
        return float("nan"), float("nan"), float("nan"), 0
    return float(v.mean()), float(v.min()), float(v.max()), int(v.size)


# --- evaluation ----------------------------------------------------------------------------------

def evaluate(images: list[EvalImage], methods: dict[str, Method], denoiser: Denoiser,
             predictor: ErrorPredictor, lambdas: Sequence[float]) -> list[Outputs]:
    """Run every method on every image; at the headline level also the λ sweep (one prepare,
    several cheap λ tails, as the service does)."""
    outputs = []
    for n, image in enumerate(images, 1):
        results = {name: method(image) for name, method in methods.items()}
        out = Outputs(image, results, predicted_error=predictor(image.frame, results[TEMPORAL]))
        if image.spp == HEADLINE_SPP:
            cache = denoiser.prepare(image.window, image.centre)
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


def headline_factor(table: dict[tuple[int, str], dict[str, float]]) -> float:
    noisy, best = table.get((HEADLINE_SPP, NOISY)), table.get((HEADLINE_SPP, TEMPORAL))
    return noisy["smape"] / best["smape"] if noisy and best and best["smape"] > 0 else float("nan")


def per_scene_headline(outputs: list[Outputs]) -> list[tuple[str, float, float]]:
    """(scene, SMAPE noisy, SMAPE temporal) at the headline level, per image."""
    return [(o.image.scene, float(smape(clean(o.results[NOISY]), o.image.reference)),
             float(smape(clean(o.results[TEMPORAL]), o.image.reference)))
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
        true = smape_map(clean(out.results[TEMPORAL]), out.image.reference).numpy()
        pred = out.predicted_error.numpy()
        rows.setdefault(out.image.spp, []).append(
            (pearson(pred, true), spearman(pred, true), float(pred.mean()), float(true.mean())))
    return {spp: {"pearson": nanstats(r[0] for r in rs), "spearman": nanstats(r[1] for r in rs),
                  "predicted": nanstats(r[2] for r in rs), "true": nanstats(r[3] for r in rs), "n": len(rs)}
            for spp, rs in sorted(rows.items())}


def flicker_rows(renderer: BuiltinRenderer, reference: Tensor, methods: dict[str, Method]) -> dict[str, tuple[float, float]]:
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


# --- crops ---------------------------------------------------------------------------------------

def crop_box(size: tuple[int, int]) -> tuple[slice, slice]:
    """The centre square of at most CROP_SIDE pixels."""
    h, w = size
    side = min(CROP_SIDE, h, w)
    y, x = (h - side) // 2, (w - side) // 2
    return slice(y, y + side), slice(x, x + side)


def enlarge(rgb8: np.ndarray) -> np.ndarray:
    factor = max(1, CROP_DISPLAY // max(rgb8.shape[:2]))
    return rgb8.repeat(factor, 0).repeat(factor, 1)


def write_crops(out: Outputs, folder: Path, stem: str) -> list[tuple[str, str]]:
    """PNG panels of one image: every method, the reference, predicted and true error maps.
    Returns (label, file name) pairs in display order."""
    ys, xs = crop_box(out.image.reference.shape[-2:])

    def hwc(t: Tensor) -> np.ndarray:
        return clean(t)[0].permute(1, 2, 0).numpy()[ys, xs]

    panels = [(name, tonemap(hwc(t))) for name, t in out.results.items()]
    panels.append(("reference", tonemap(hwc(out.image.reference))))
    true = smape_map(clean(out.results[TEMPORAL]), out.image.reference)[0, 0].numpy()[ys, xs]
    pred = out.predicted_error[0, 0].numpy()[ys, xs]
    vmax = float(np.percentile(true, 99)) or 1.0  # same scale for both, so they compare directly
    panels += [("predicted error", false_colour(pred, vmax)), ("true SMAPE", false_colour(true, vmax))]
    files = []
    for label, rgb8 in panels:
        name = f"{stem}_{label.split(' (')[0].replace(' ', '-').replace('.', '')}.png"
        write_png(folder / name, enlarge(rgb8))
        files.append((label, name))
    return files


def pick_example(outputs: list[Outputs], prefer: str | None = None) -> Outputs | None:
    """At the headline level: the preferred scene if present, else the median temporal SMAPE
    (a representative image, not the best one)."""
    candidates = [o for o in outputs if o.image.spp == HEADLINE_SPP]
    if not candidates:
        return None
    for o in candidates:
        if o.image.scene == prefer:
            return o
    ranked = sorted(candidates, key=lambda o: float(smape(clean(o.results[TEMPORAL]), o.image.reference)))
    return ranked[len(ranked) // 2]


# --- the markdown --------------------------------------------------------------------------------

def fmt(x: float, spec: str = ".4f") -> str:
    return format(x, spec) if np.isfinite(x) else "n/a"


def markdown_quality(title: str, table: dict[tuple[int, str], dict[str, float]], methods: Sequence[str]) -> str:
    lines = [f"### {title}", "",
             "| spp | method | SMAPE | relMSE | PSNR (dB) | 1−SSIM | SMAPE ÷ (noisy / method) |",
             "|---:|---|---:|---:|---:|---:|---:|"]
    for spp in sorted({s for s, _ in table}):
        base = table[(spp, NOISY)]["smape"]
        for name in methods:
            row = table.get((spp, name))
            if row is None:
                continue
            emphasis = "**" if name == TEMPORAL else ""
            factor = base / row["smape"] if row["smape"] > 0 else float("nan")
            lines.append(f"| {spp} | {emphasis}{name}{emphasis} | {fmt(row['smape'])} | {fmt(row['relmse'])} | "
                         f"{fmt(row['psnr'], '.2f')} | {fmt(row['dssim'])} | {fmt(factor, '.2f')}× |")
    return "\n".join(lines) + "\n"


def markdown_lambda(title: str, table: dict[float, dict[str, float]]) -> str:
    lines = [f"### {title}", "",
             "| λ | SMAPE | residual noise (flat HF error) | detail (HF energy ratio) | gradient correlation |",
             "|---:|---:|---:|---:|---:|"]
    for lam, row in table.items():
        lines.append(f"| {lam:g} | {fmt(row['smape'])} | {fmt(row['noise'], '.5f')} | {fmt(row['detail'], '.3f')} | "
                     f"{fmt(row['grad_corr'], '.3f')} |")
    return "\n".join(lines) + "\n"


def markdown_pyramid(outputs: list[Outputs]) -> str:
    """Mean of `pyramid_levels` over the images that have it, one row per coarse level."""
    rows = [out.pyramid for out in outputs if out.pyramid]
    if not rows:
        return "The network has no coarse levels (single-scale)."
    lines = ["| level (resolution) | SMAPE of its own result | finest result pooled | noisy input pooled | mean α joining the finer level |",
             "|---|---:|---:|---:|---:|"]
    for level in range(len(rows[0])):
        mean = {key: float(np.mean([r[level][key] for r in rows])) for key in rows[0][level]}
        lines.append(f"| {level + 1} (1/{2 ** (level + 1)}) | {fmt(mean['own'])} | {fmt(mean['pooled_finest'])} "
                     f"| {fmt(mean['pooled_noisy'])} | {fmt(mean['alpha'], '.3f')} |")
    return "\n".join(lines)


def markdown_error(title: str, table: dict[int, dict[str, tuple]]) -> str:
    lines = [f"### {title}", "",
             "| spp | images | Pearson mean [min, max] | Spearman mean [min, max] | mean predicted SMAPE | mean true SMAPE |",
             "|---:|---:|---|---|---:|---:|"]

    def stat(s: tuple) -> str:
        mean, lo, hi, n = s
        return f"{fmt(mean, '.3f')} [{fmt(lo, '.3f')}, {fmt(hi, '.3f')}]" if n else "n/a"

    for spp, row in table.items():
        lines.append(f"| {spp} | {row['n']} | {stat(row['pearson'])} | {stat(row['spearman'])} | "
                     f"{fmt(row['predicted'][0])} | {fmt(row['true'][0])} |")
    return "\n".join(lines) + "\n"


def markdown_crops(title: str, files: list[tuple[str, str]], caption: str) -> str:
    header = "| " + " | ".join(label for label, _ in files) + " |"
    rule = "|" + "---|" * len(files)
    cells = "| " + " | ".join(f"![{label}]({CROPS_DIR}/{name})" for label, name in files) + " |"
    return f"### {title}\n\n{caption}\n\n{header}\n{rule}\n{cells}\n"


def shown_path(path: Path) -> str:
    """A path as the reader would type it: relative to the working directory when inside it."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def weights_line(model: torch.nn.Module, path: Path) -> str:
    extra = getattr(model, "checkpoint_extra", {}) or {}
    config = ", ".join(f"{k}={v}" for k, v in dataclasses.asdict(model.config).items())
    produced = extra.get("command")
    best = f"best validation {extra['val']:.4f} at step {extra['step']}; " if "val" in extra and "step" in extra else ""
    size_mb = path.stat().st_size / 1e6
    return (f"`{shown_path(path)}` ({size_mb:.2f} MB; {best}{config})"
            + (f", produced by `{produced}`" if produced else ""))


# --- entry point ---------------------------------------------------------------------------------

def run_quality_report(
    data_dir: str | Path,
    out_dir: str | Path,
    *,
    weights_dir: str | Path = SHIPPED_WEIGHTS_DIR,
    builtin_scenes: Sequence[str] = ("cornell-box", "glossy-spheres", "fireflies"),
    builtin_size: int = 64,
    reference_spp: int = 2048,
    lambdas: Sequence[float] = LAMBDAS,
    use_oidn: bool = True,
    cache_dir: str | Path | None = None,
    threads: int = 1,
) -> Path:
    """Evaluate the trained denoiser and error predictor and write OUT/denoiser.md (+ OUT/denoiser/*.png).

    weights_dir: where denoiser.pt and error_predictor.pt are (default: the shipped weights).
    reference_spp: samples per pixel of the built-in scenes' references (the test uses few).
    cache_dir: where those references are kept between runs (default DATA/quality-cache).
    threads: torch intra-op threads. One by default: on the shared 2-core machine, with a data-set
    build and a training run beside it, two threads made a 64² forward pass 6–16× slower
    (OpenMP workers waiting on busy cores), and these images are too small to need more.
    """
    with pinned_torch_threads(threads):  # called in-process by `bench`: leave no global change
        return _run(Path(data_dir), Path(out_dir), Path(weights_dir), builtin_scenes, builtin_size,
                    reference_spp, lambdas, use_oidn, cache_dir)


def _run(data_dir: Path, out_dir: Path, weights_dir: Path, builtin_scenes: Sequence[str], builtin_size: int,
         reference_spp: int, lambdas: Sequence[float], use_oidn: bool, cache_dir: str | Path | None) -> Path:
    started = time.perf_counter()
    cache = Path(cache_dir) if cache_dir is not None else data_dir / "quality-cache"
    denoiser_path, predictor_path = weights_dir / DENOISER_FILE, weights_dir / ERROR_PREDICTOR_FILE
    denoiser = load_checkpoint(denoiser_path, expected_kind=Denoiser.kind)
    predictor = load_checkpoint(predictor_path, expected_kind=ErrorPredictor.kind)
    crops_dir = out_dir / CROPS_DIR

    with torch.no_grad():
        methods, oidn_note = make_methods(denoiser, use_oidn)
        names = list(methods)

        log(f"held-out split of {data_dir}")
        held_images, held_entry = heldout_images(data_dir, denoiser.config.temporal_radius)
        held = evaluate(held_images, methods, denoiser, predictor, lambdas)
        del held_images

        built: list[Outputs] = []
        flicker_tables: dict[str, dict[str, tuple[float, float]]] = {}
        reference_noise: dict[str, float] = {}
        for name in builtin_scenes:
            log(f"built-in scene {name} at {builtin_size}²")
            renderer = BuiltinRenderer(name, builtin_size)
            reference, reference_noise[name] = builtin_reference(renderer, reference_spp, cache)
            built += evaluate(builtin_images(renderer, reference), methods, denoiser, predictor, lambdas)
            flicker_tables[name] = flicker_rows(renderer, reference, methods)

        held_table, built_table = quality_table(held, names), quality_table(built, names)
        factor = headline_factor(held_table)
        sections = {
            "held_quality": markdown_quality("Held-out procedural scenes", held_table, names),
            "built_quality": markdown_quality("Built-in scenes", built_table, names) if built else "",
            "held_lambda": markdown_lambda(f"Held-out scenes, {HEADLINE_SPP} spp", lambda_table(held)),
            "built_lambda": markdown_lambda(f"Built-in scenes, {HEADLINE_SPP} spp", lambda_table(built)) if built else "",
            "held_error": markdown_error("Held-out scenes", error_predictor_table(held)),
            "pyramid": markdown_pyramid(held),
            "built_error": markdown_error("Built-in scenes", error_predictor_table(built)) if built else "",
        }
        crops = []
        for stale in crops_dir.glob("*.png"):   # the example images change with the data: no orphans
            stale.unlink()
        for group, outs, prefer in (("heldout", held, None), ("builtin", built, "fireflies")):
            example = pick_example(outs, prefer)
            if example is not None:
                files = write_crops(example, crops_dir, f"{group}_{example.image.scene.replace('/', '_')}")
                crops.append(markdown_crops(
                    f"{example.image.group}: {example.image.scene}, {example.image.spp} spp", files,
                    f"Centre crop of at most {CROP_SIDE}² pixels, enlarged with nearest-neighbour. Error maps: "
                    f"predicted vs true per-pixel SMAPE of the temporal result, same colour scale "
                    f"(black 0 → white at the 99th percentile of the true error)."))

    path = write_report(out_dir, data_dir=data_dir, denoiser=denoiser, denoiser_path=denoiser_path,
                        predictor=predictor, predictor_path=predictor_path, held_entry=held_entry,
                        n_held=len({o.image.scene for o in held}), builtin_scenes=builtin_scenes,
                        builtin_size=builtin_size, reference_spp=reference_spp, cache=cache,
                        factor=factor, per_scene=per_scene_headline(held), sections=sections,
                        flicker_tables=flicker_tables, reference_noise=reference_noise, names=names, oidn_note=oidn_note, crops=crops,
                        seconds=time.perf_counter() - started)
    log(f"wrote {path} (headline: 16-spp SMAPE reduction {factor:.2f}× on held-out scenes)")
    return path


def write_report(out_dir: Path, *, data_dir: Path, denoiser: Denoiser, denoiser_path: Path,
                 predictor: ErrorPredictor, predictor_path: Path, held_entry: dict, n_held: int,
                 builtin_scenes: Sequence[str], builtin_size: int, reference_spp: int, cache: Path,
                 factor: float, per_scene: list[tuple[str, float, float]], sections: dict[str, str],
                 flicker_tables: dict[str, dict[str, tuple[float, float]]], reference_noise: dict[str, float],
                 names: list[str],
                 oidn_note: str | None, crops: list[str], seconds: float) -> Path:

    window = 2 * held_entry["radius"] + 1
    verdict = ("meets" if factor >= 3 else "falls short of") if np.isfinite(factor) else "cannot be checked against"
    gap = "" if not np.isfinite(factor) or factor >= 3 else (
        "\nBelow target. Levers not measured here, in the order we would try them: more training "
        "scenes (the held-out scenes come from the same generator as the training scenes, so more of "
        "the same data should transfer directly), more optimiser steps and larger crops (the CPU recipe "
        "is sized to about an hour), a wider network (`--width`), and the bigger GPU recipe.\n")
    low_reference = "" if held_entry["reference_spp"] >= 8 * PROGRESSIVE_STEPS[-1][0] else (
        f" The held-out references have only {held_entry['reference_spp']} spp, so at the higher input "
        "levels part of every error is the reference's own noise, and denoised results are penalised "
        "for being cleaner than it.")
    per_scene_rows = "\n".join(f"| {s} | {fmt(n)} | {fmt(t)} | {fmt(n / t if t > 0 else float('nan'), '.2f')}× |"
                               for s, n, t in per_scene)
    flicker_md = []
    for scene, rows in flicker_tables.items():
        flicker_md.append(f"**{scene}** ({builtin_size}², {len(FLICKER_SEEDS) - 2} denoised frames)\n\n"
                          "| method | mean abs Δ, linear ÷ mean reference | mean abs Δ, sRGB 0–255 |\n|---|---:|---:|\n"
                          + "\n".join(f"| {name} | {fmt(rows[name][0])} | {fmt(rows[name][1], '.2f')} |"
                                      for name in names) + "\n")
    noise_line = ", ".join(f"{scene} {fmt(value, '.3f')}" for scene, value in reference_noise.items()) or "n/a"
    complete = "" if held_entry.get("complete") else " **(the split's build was not complete: finished items only)**"
    text = f"""# Denoiser quality

{provenance(REPORT_COMMAND.format(data=data_dir), active_variant())}
The whole report took {seconds / 60:.1f} minutes.

Weights: denoiser {weights_line(denoiser, denoiser_path)}; error predictor {weights_line(predictor, predictor_path)}.

## Headline

**SMAPE reduction of {HEADLINE_SPP}-spp inputs on held-out scenes: {fmt(factor, '.2f')}×**
(mean SMAPE of the noisy input ÷ mean SMAPE of the temporal multi-scale result, λ = 1), which
{verdict} the 3× target.
{gap}
## What is compared

- **noisy input**: the Monte Carlo mean the renderer accumulated.
- **single-frame KPCN**: the trained network with multi-scale compositing and the temporal
  stage switched off — finest pyramid level only, one frame.
- **multi-scale (1 frame)**: the trained network on the centre frame alone (3-level pyramid
  and compositor, no neighbours).
- **temporal multi-scale**: the trained network on a {window}-frame window (what the loop runs
  for sequences).
{f"- **OIDN**: {oidn_note}" if oidn_note and OIDN in names else ""}

These are **ablations of the one trained network**, not separately trained models: every
row uses the same weights, with stages switched off. The trainer cuts half of its windows to
the centre frame, so the one-frame multi-scale row is a setting the network was trained for.
The single-scale row is not: in training the finest level's result always went through the
compositor, and the trunk it shares with the coarse levels was also trained for them. The
README's "Shipped weights" compares the separately trained stage networks (single-scale,
+ compositor, + temporal), which is the cleaner measure of what each stage adds.
{"" if OIDN in names else f"OIDN: {oidn_note}"}

Metrics per image, then the mean over images at each level: SMAPE (ε = 0.01, Vogels et al.
eq. 2) and relMSE (ε = 0.01) on linear HDR radiance; PSNR and SSIM (Wang et al., 11×11
gaussian window) on the clamped sRGB display image in [0, 1].

Held-out data: `{data_dir}`, split `heldout`: {n_held} windows of {window} frames from
{held_entry['scenes']} procedural scenes ({held_entry['frames']} frames each, {held_entry['size']}²,
reference {held_entry['reference_spp']} spp, uniform input levels 16/32/64/128 spp total),
built by `{held_entry.get('command', '?')}`{complete}. Held-out seeds are disjoint from training seeds.{low_reference}
The held-out references' own noise, as the mean relative standard error of their pixels (same ε):
{fmt(held_entry.get('reference_noise', float('nan')), '.4f')}. Against a reference with relative standard error σ, even the exact image
scores a SMAPE of about 0.4·σ (|d − r| / 2r with gaussian noise: √(2/π) / 2 ≈ 0.4), so held-out SMAPE
figures near {fmt(0.4 * held_entry.get('reference_noise', float('nan')), '.4f')} are the references' noise, not the denoiser's error.

Built-in scenes: {', '.join(builtin_scenes) or 'none'} at {builtin_size}², rendered here with the
loop's renderer and integrator; inputs 16 → 32 → 64 → 128 spp progressively, reference
{reference_spp} spp with its own seed (cached in `{cache}`); the references' own noise, as the mean
relative standard error of their pixels: {noise_line}. Error figures well below that level
are not resolvable on that scene. The built-ins are static, so their
{len(SEQUENCE_SEEDS)}-frame window is the same view rendered with {len(SEQUENCE_SEEDS)} seeds — what the loop
renders for `--frames {len(SEQUENCE_SEEDS)}` of a static scene. The temporal row therefore sees
{len(SEQUENCE_SEEDS)}× the samples of the other rows there; on held-out scenes the neighbours are
other camera positions, warped along motion vectors.

## Quality per sample count

{sections['held_quality']}
{sections['built_quality']}
### Per held-out image at {HEADLINE_SPP} spp

| image | SMAPE noisy | SMAPE temporal | reduction |
|---|---:|---:|---:|
{per_scene_rows}

## Pyramid levels

Held-out scenes, {HEADLINE_SPP} spp, λ = 1, temporal window: each coarse level's own filtered
result against the reference pooled to its resolution (all demodulated by albedo), next to
the finest result and the noisy input pooled the same way, and the scale compositor's mean α
(eq. 5) where the level's result enters the next finer one. A coarse level earns its α where
its own result beats the pooled finest result.

{sections['pyramid']}

## Temporal flicker

A static view rendered {len(FLICKER_SEEDS)} times at {FLICKER_SPP} spp with different seeds is treated
as a {len(FLICKER_SEEDS)}-frame sequence without motion. Frames 2–{len(FLICKER_SEEDS) - 1} are denoised
(temporal: window of the previous, the frame and the next; the others: the frame alone) and the
mean absolute difference between consecutive results is reported — a static scene should not
change at all, so every bit of it is flicker.

{chr(10).join(flicker_md)}
## λ: residual noise vs detail

The temporal multi-scale result at {HEADLINE_SPP} spp with a global λ; all λ values come from one
`prepare` and cheap λ tails, as the service re-denoises. Measures on L = log(1 + luminance)
(Rec. 709 weights), with the high-pass HP(x) = x − 3×3 box blur of x:

- **residual noise**: mean |HP(L(denoised)) − HP(L(reference))| over *flat* pixels — those whose
  reference gradient magnitude is in the lower half of the image. There the reference has no
  fine detail, so pixel-scale error is left-over noise. Lower is cleaner.
- **detail (HF energy ratio)**: mean |HP(L(denoised))| ÷ mean |HP(L(reference))| over *detail*
  pixels (top quarter of reference gradient magnitude). 1 = as much fine structure as the
  reference; < 1 = blurred; > 1 = extra (noise).
- **gradient correlation**: Pearson correlation of the central-difference gradient magnitudes of
  L(denoised) and L(reference) over the whole image; closer to 1 = edges in the right places.

Larger λ penalises errors that move the result away from the input (blur, lost detail, eq. 6),
so noise should rise and detail rise with it.

{sections['held_lambda']}
{sections['built_lambda']}
## Error predictor vs true SMAPE

Per image: the predicted per-pixel SMAPE map against the true per-pixel SMAPE of the temporal
multi-scale result (λ = 1, the pair the loop uses to allocate samples), Pearson and Spearman
over pixels; mean and range over images. Spearman matters most: the allocator only needs the
ranking to be right. (`renderloop train` fits the predictor to the one-frame result; for
sequences the loop hands it the temporal one, and that is the pairing measured here.)

{sections['held_error']}
{sections['built_error']}
## Crops

{chr(10).join(crops) if crops else 'No images at the headline level.'}
"""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / REPORT_NAME
    path.write_text(text)
    return path
