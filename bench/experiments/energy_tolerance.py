"""How much should the denoised image's mean be pulled towards the samples'? (models/energy.py;
docs/decisions.md, "The energy factor")

models.energy trusts the samples' mean with weight 1 / (1 + (rse/τ)²): an inverse-variance blend
of an unbiased estimate (relative standard error rse) with the denoiser's own total, whose error
is about τ. So τ is a measurement, not a taste: the RMS over scenes of the untouched output's
energy error (mean radiance ÷ the reference's − 1). Per scene and sample count: that error, the
samples' rse, and the energy, SMAPE and relMSE the factor gives for each candidate τ; last, the
RMS error per sample count — the τ the formula asks for. One render and one preparation per
scene and level, shared by every τ (the factor is a post-step).

    python -m bench.experiments.energy_tolerance [--suite val|dev] [--spp 16 64 256] [--tau 0.01 0.03] [--weights DIR]
    python -m bench.experiments.energy_tolerance --megapixels 2 --scenes fog_spot misty_lantern --spp 16 32 [--pool 1 4 16]
    python -m bench.experiments.energy_tolerance --megapixels 0.016428 --scenes fog_spot --spp 16 32 64 \
        --reference-spp 16384 --render-references --cache /tmp/refs      # 0.016428 MP: fog_spot's own 148×111

With --megapixels, the named suite scenes as written at that film size (bench.versus_mitsuba_scene),
rendered by the loop with uniform allocation (16 spp, then doubling), against the references
`renderloop bench --versus-mitsuba` left in the bench cache (--cache); a scene without one is
skipped, since rendering it takes hours here, unless --render-references asks for it. Beside each
image's energy: its median pixel ÷ the reference's, which says whether a factor that restores the
total also fits the typical pixel.

A reference of a scene whose light arrives by rare paths is itself heavy-tailed: its typical pixel
sits below the true mean by an amount that shrinks with its spp (fog_spot: a 1024-spp reference's
median pixel 3.3 % below a 16384-spp one's, docs/decisions.md), and per-pixel SMAPE against it then
rewards an image that drops the rare paths' energy. Two ways to see past it: the same images
against references of more spp (--reference-spp, --render-references), and --pool K: the metrics
also on K×K block means of image and reference, where the reference's noise falls by K and a bias
in the low frequencies (the energy) is what remains.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from bench.common import denoiser_settings, image_metrics, load_bench_networks, pinned_torch_threads
from bench.dev_references import SUITES, DevScene, dev_scenes, load_reference
from bench.loop_report import DEFAULT_CACHE_DIR
from bench.quality_measures import block_means
from bench.suite_quality import uniform_render
from bench.versus_mitsuba import suite_scenes
from bench.versus_mitsuba_run import FIRST_SPP, make_loop, spp_levels
from bench.versus_mitsuba_scene import reference, reference_path, scaled_film
from models.denoiser import Denoiser, DenoiserCache
from models.frames import FrameTensors
from service.loop.denoise_frame import prepare_frame
from service.loop.tensors import frame_tensors, to_image

UNTOUCHED = 1e-9   # a τ this small trusts the samples with weight ~0: the denoiser's own energy


def outputs_per_tolerance(denoiser: Denoiser, cache: DenoiserCache, taus: list[float]) -> list[np.ndarray]:
    """The λ = 1 image for each τ from one preparation; the denoiser's config is back in place afterwards."""
    images = []
    for tau in taus:
        with denoiser_settings(denoiser, energy_tolerance=tau):
            images.append(to_image(denoiser.apply(cache)))
    return images


def suite_frames(suite: str, spp_totals: list[int], networks) -> Iterator[tuple[DevScene, int, FrameTensors, np.ndarray]]:
    """(scene, spp, uniform render, reference) for each scene of a suite at its own size."""
    for scene in dev_scenes(None, SUITES[suite].root):
        ref, _ = load_reference(SUITES[suite].references, scene, None if scene.frames == 1 else 0)
        for spp in spp_totals:
            yield scene, spp, frame_tensors(uniform_render(scene, spp, networks).buffers[0]), ref


def scaled_frames(names: list[str] | None, megapixels: float, spp_totals: list[int], networks, cache_dir: Path,
                  reference_spp: int, render_references: bool = False) -> Iterator[tuple[DevScene, int, FrameTensors, np.ndarray]]:
    """The same for suite scenes as written at `megapixels`, against the bench cache's
    `--versus-mitsuba` references of `reference_spp` (rendered into it first if `render_references`);
    the loop's uniform iterations give 16, 32, 64 … spp."""
    iterations = len(spp_levels(max(spp_totals)))
    for scene in suite_scenes(names):
        film = scaled_film(scene, megapixels)
        if not render_references and not reference_path(scene, film, reference_spp, cache_dir).is_file():
            print(f"{scene.name}: no cached {reference_spp}-spp reference at {film.width}×{film.height}, skipped "
                  "(--render-references renders it)", flush=True)
            continue
        ref = reference(scene, film, reference_spp, cache_dir).mean
        loop = make_loop(scene, film, networks, "uniform", iterations)
        for record in loop.run():
            if round(record.spp_mean) in spp_totals:
                yield scene, round(record.spp_mean), frame_tensors(loop.state.buffers[0]), ref


def median_pixel_ratio(image: np.ndarray, ref: np.ndarray) -> float:
    """The median over pixels of the image's channel mean ÷ the reference's: the typical pixel's energy."""
    return float(np.median(image.mean(-1) / np.maximum(ref.mean(-1), 1e-6)))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--spp", type=int, nargs="+", default=[16, 64, 256])
    parser.add_argument("--tau", type=float, nargs="+", default=[0.01, 0.03])
    parser.add_argument("--weights", default=None, help="folder of denoiser.pt and error_predictor.pt (default: shipped)")
    parser.add_argument("--megapixels", type=float, default=None,
                        help="suite scenes as written at this film size, against cached --versus-mitsuba references")
    parser.add_argument("--scenes", nargs="+", default=None, help="with --megapixels: which suite scenes (default: all)")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE_DIR, help="the bench cache holding the references")
    parser.add_argument("--reference-spp", type=int, default=1024, help="with --megapixels: the cached references' spp")
    parser.add_argument("--render-references", action="store_true",
                        help="with --megapixels: render a reference the cache lacks (mi.render, `independent` sampler)")
    parser.add_argument("--pool", type=int, nargs="+", default=[1],
                        help="the metrics also on K×K block means of image and reference (1: per pixel)")
    args = parser.parse_args()
    if any(t <= 0 for t in args.tau):
        parser.error("--tau values must be > 0")
    if any(k < 1 for k in args.pool):
        parser.error("--pool values must be ≥ 1")
    if args.render_references and not args.megapixels:
        parser.error("--render-references needs --megapixels (the suites' own references are committed)")
    if args.megapixels and not set(args.spp) <= set(spp_levels(max(*args.spp, FIRST_SPP))):
        parser.error(f"with --megapixels, --spp values are the loop's totals: {', '.join(map(str, spp_levels(64)))} …")
    nets = load_bench_networks(args.weights)
    denoiser = nets.networks.denoiser
    # The cache keeps the samples' mean only when the config asks for the factor.
    denoiser.config = dataclasses.replace(denoiser.config, energy_tolerance=denoiser.config.energy_tolerance or 1.0)
    taus = [UNTOUCHED, *args.tau]
    frames = (scaled_frames(args.scenes, args.megapixels, args.spp, nets.networks, args.cache, args.reference_spp,
                            args.render_references) if args.megapixels
              else suite_frames(args.suite, args.spp, nets.networks))
    head = " | ".join(f"τ = {t:g}: energy, median pixel, SMAPE, relMSE" for t in args.tau)
    print(f"| scene | spp | pool | samples' rse | noisy energy | OIDN energy, median pixel, SMAPE, relMSE "
          f"| untouched: energy, median pixel, SMAPE, relMSE | {head} |\n"
          "|---|---:|---:|---:|---:|---|---|" + "---|" * len(args.tau))
    errors: dict[int, list[float]] = {}
    with pinned_torch_threads(2), torch.no_grad():
        for scene, spp, frame, ref in frames:
            mean = float(ref.mean())
            prepared = prepare_frame(denoiser, [frame], 0)
            cache, candidate = prepared.cache, prepared.candidate
            images = outputs_per_tolerance(denoiser, cache, taus)
            errors.setdefault(spp, []).append(float(images[0].mean()) / mean - 1.0)
            for k in args.pool:
                pooled_ref = block_means(ref, k)
                cells = []
                for image in [to_image(candidate), *images]:
                    pooled = block_means(image, k)
                    m = image_metrics(pooled, pooled_ref)
                    cells.append(f"{image.mean() / mean:.4f}, {median_pixel_ratio(pooled, pooled_ref):.4f}, "
                                 f"{m['smape']:.4f}, {m['relmse']:.3g}")
                print(f"| {scene.name} | {spp} | {k} | {float(cache.energy.rse[0]):.4f} | {to_image(frame.color).mean() / mean:.4f} "
                      "| " + " | ".join(cells) + " |", flush=True)
    print("\n| spp | RMS energy error of the untouched output (the τ models.energy asks for) |\n|---:|---:|")
    for spp, values in errors.items():
        print(f"| {spp} | {math.sqrt(float(np.mean(np.square(values)))):.4f} |")


if __name__ == "__main__":
    main()
