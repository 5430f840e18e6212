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
"""
from __future__ import annotations

import argparse
import dataclasses
import math

import numpy as np
import torch

from bench.common import denoiser_settings, image_metrics, load_bench_networks, pinned_torch_threads
from bench.dev_references import SUITES, dev_scenes, load_reference
from bench.suite_quality import uniform_render
from models.denoiser import Denoiser, DenoiserCache
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


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--spp", type=int, nargs="+", default=[16, 64, 256])
    parser.add_argument("--tau", type=float, nargs="+", default=[0.01, 0.03])
    parser.add_argument("--weights", default=None, help="folder of denoiser.pt and error_predictor.pt (default: shipped)")
    args = parser.parse_args()
    if any(t <= 0 for t in args.tau):
        parser.error("--tau values must be > 0")
    nets = load_bench_networks(args.weights)
    denoiser = nets.networks.denoiser
    # The cache keeps the samples' mean only when the config asks for the factor.
    denoiser.config = dataclasses.replace(denoiser.config, energy_tolerance=denoiser.config.energy_tolerance or 1.0)
    taus = [UNTOUCHED, *args.tau]
    head = " | ".join(f"τ = {t:g}: energy, SMAPE, relMSE" for t in args.tau)
    print(f"| scene | spp | samples' rse | noisy energy | OIDN energy | untouched: energy, SMAPE, relMSE | {head} |\n"
          "|---|---:|---:|---:|---:|---|" + "---|" * len(args.tau))
    errors: dict[int, list[float]] = {}
    with pinned_torch_threads(2), torch.no_grad():
        for scene in dev_scenes(None, SUITES[args.suite].root):
            reference, _ = load_reference(SUITES[args.suite].references, scene, None if scene.frames == 1 else 0)
            mean = float(reference.mean())
            for spp in args.spp:
                frame = frame_tensors(uniform_render(scene, spp, nets.networks).buffers[0])
                prepared = prepare_frame(denoiser, [frame], 0)
                cache, candidate = prepared.cache, prepared.candidate
                images = outputs_per_tolerance(denoiser, cache, taus)
                errors.setdefault(spp, []).append(float(images[0].mean()) / mean - 1.0)
                cells = []
                for image in images:
                    m = image_metrics(image, reference)
                    cells.append(f"{image.mean() / mean:.4f}, {m['smape']:.4f}, {m['relmse']:.3g}")
                print(f"| {scene.name} | {spp} | {float(cache.energy.rse[0]):.4f} | {to_image(frame.color).mean() / mean:.4f} "
                      f"| {to_image(candidate).mean() / mean:.4f} | " + " | ".join(cells) + " |", flush=True)
    print("\n| spp | RMS energy error of the untouched output (the τ models.energy asks for) |\n|---:|---:|")
    for spp, values in errors.items():
        print(f"| {spp} | {math.sqrt(float(np.mean(np.square(values)))):.4f} |")


if __name__ == "__main__":
    main()
