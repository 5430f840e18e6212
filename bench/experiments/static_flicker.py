"""Can a single-frame setting make ours steadier than OIDN on a static sequence? (the static
flicker of `renderloop bench --denoiser`, docs/suite-quality.md; the post-training settings)

The goal is temporal flicker on a static sequence at most OIDN's. Per still scene, FRAMES
renders of the same view at 16 spp, each with its own seed (as `renderloop bench --denoiser`
makes its static sequences), each denoised alone; per post-training setting of the shipped
network (one preparation per frame serves them all): flicker = mean |Δ| between consecutive
frames (the reference is fixed, so this is the residual's change) ÷ OIDN's, and frame 0's SMAPE
and relMSE ÷ OIDN's. Last, per setting: scenes at most OIDN's flicker, and the medians.

    python -m bench.experiments.static_flicker [--suite val|dev] [--weights DIR]
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from bench.common import denoiser_settings, image_metrics, load_bench_networks, pinned_torch_threads
from bench.dev_references import SUITES, still_scenes
from bench.quality_measures import mean_abs_change
from bench.suite_quality import SEED, uniform_render
from service.loop.denoise_frame import prepare_frame
from service.loop.tensors import frame_tensors, to_image

FRAMES = 4
SPP = 16
# name → changes to the shipped config (models.denoiser.DenoiserConfig's post-training settings)
SETTINGS: dict[str, dict] = {
    "shipped": {},
    "τ off": {"energy_tolerance": 1e-9},
    "τ 0.01": {"energy_tolerance": 0.01},
    "τ 0.03": {"energy_tolerance": 0.03},
    "clamp 0.1": {"kernel_clamp": 0.1},
    "clamp 0.25": {"kernel_clamp": 0.25},
    "clamp 0.5": {"kernel_clamp": 0.5},
    "b 0": {"gate_offset": 0.0},
    "b 4": {"gate_offset": 4.0},
}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--weights", default=None, help="folder of denoiser.pt and error_predictor.pt (default: shipped)")
    args = parser.parse_args()
    nets = load_bench_networks(args.weights)
    denoiser = nets.networks.denoiser
    if denoiser.config.energy_tolerance <= 0:
        parser.error("the τ settings need a checkpoint with energy_tolerance > 0 (its cache keeps the samples' mean)")
    print("Each cell: flicker / SMAPE / relMSE ÷ OIDN's (< 1: ours better)\n\n| scene | "
          + " | ".join(SETTINGS) + " |\n|---|" + "---:|" * len(SETTINGS))
    ratios: dict[str, list[tuple[float, float, float]]] = {name: [] for name in SETTINGS}
    with pinned_torch_threads(2), torch.no_grad():
        for scene, reference in still_scenes(args.suite):   # an animated scene is not a static sequence
            ours: dict[str, list[np.ndarray]] = {name: [] for name in SETTINGS}
            oidn = []
            for f in range(FRAMES):
                frame = frame_tensors(uniform_render(scene, SPP, nets.networks, seed=SEED + f).buffers[0])
                prepared = prepare_frame(denoiser, [frame], 0)
                oidn.append(to_image(prepared.candidate))
                cache = prepared.cache
                for name, changes in SETTINGS.items():
                    with denoiser_settings(denoiser, **changes):
                        ours[name].append(to_image(denoiser.apply(cache)))
            base, first = mean_abs_change(oidn), image_metrics(oidn[0], reference)
            cells = []
            for name, images in ours.items():
                m = image_metrics(images[0], reference)
                ratio = (mean_abs_change(images) / base, m["smape"] / first["smape"], m["relmse"] / first["relmse"])
                ratios[name].append(ratio)
                cells.append(" / ".join(f"{r:.3f}" for r in ratio))
            print(f"| {scene.name} | " + " | ".join(cells) + " |", flush=True)
    print("\n| setting | flicker ≤ OIDN | median flicker ÷ OIDN | median SMAPE ÷ OIDN | median relMSE ÷ OIDN |\n"
          "|---|---:|---:|---:|---:|")
    for name, values in ratios.items():
        flicker, s, r = np.array(values).T
        print(f"| {name} | {(flicker <= 1).sum()} of {len(flicker)} | {np.median(flicker):.3f} | {np.median(s):.3f} "
              f"| {np.median(r):.3f} |")


if __name__ == "__main__":
    main()
