"""Should the samples' energy be restored block by block as well as image-wide? (docs/models.md,
"Energy, block by block"; models/energy.py)

The image-wide factor (`energy_tolerance`) puts back what the denoiser lost wherever it lost it,
spread evenly over the frame; `energy_block` B then restores each B×B block's samples' total
with the same inverse-variance trust. Per scene, sample count and seed: one uniform render,
OIDN on the same noisy colour, albedo and normal, and ours at each block size (0 = image-wide
only). Each cell is ours ÷ OIDN (SMAPE / relMSE), the geometric mean over the seeds; the summary
gives the medians over the scenes, how many scenes are at most OIDN's, and the mean of the six
medians (16/64/256 spp × SMAPE/relMSE) that chose every earlier post-training setting.

    python -m bench.experiments.energy_blocks [--suite val|dev] [--spp 16 64 256] [--blocks 0 32 64]
                                              [--seeds 1 2 3] [--weights DIR]
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from bench.common import denoiser_settings, image_metrics, load_bench_networks, oidn_denoiser, pinned_torch_threads
from bench.dev_references import SUITES, dev_scenes, load_reference
from bench.experiments.seed_spread import paired_ratio
from bench.suite_quality import uniform_render
from models.denoiser import Denoiser
from models.frames import FrameTensors
from service.loop.oidn import candidate_for
from service.loop.tensors import frame_tensors, to_image


def block_images(denoiser: Denoiser, frame: FrameTensors, candidate: torch.Tensor, blocks: list[int]) -> list[np.ndarray]:
    """The λ = 1 image for each energy block size (0: image-wide only); the config is back in place after."""
    images = []
    for block in blocks:
        with denoiser_settings(denoiser, energy_block=block):
            images.append(to_image(denoiser.apply(denoiser.prepare([frame], 0, candidate))))
    return images


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--spp", type=int, nargs="+", default=[16, 64, 256])
    parser.add_argument("--blocks", type=int, nargs="+", default=[0, 32, 64])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--weights", default=None, help="folder of denoiser.pt and error_predictor.pt (default: shipped)")
    args = parser.parse_args()
    if any(b < 0 for b in args.blocks):
        parser.error("--blocks must be >= 0")
    nets = load_bench_networks(args.weights)
    denoiser = nets.networks.denoiser
    if denoiser.config.energy_tolerance <= 0:
        parser.error("the weights' config has no energy_tolerance: there is no energy step to refine")
    oidn, _ = oidn_denoiser()
    suite = SUITES[args.suite]
    print(f"ours ÷ OIDN, SMAPE / relMSE, geometric mean over seeds {args.seeds} (τ = {denoiser.config.energy_tolerance:g})\n\n"
          "| scene | spp | " + " | ".join(f"block {b}" for b in args.blocks) + " |\n|---|---:|" + "---|" * len(args.blocks))
    cells: dict[tuple[int, int], list[tuple[float, float]]] = {}
    with pinned_torch_threads(2), torch.no_grad():
        for scene in dev_scenes(None, suite.root):
            reference, _ = load_reference(suite.references, scene, None if scene.frames == 1 else 0)
            for spp in args.spp:
                # per block: (ours, OIDN) SMAPE and relMSE, one row per seed
                per_block: dict[int, list[tuple[float, float, float, float]]] = {b: [] for b in args.blocks}
                for seed in args.seeds:
                    buffer = uniform_render(scene, spp, nets.networks, seed=seed).buffers[0]
                    theirs = image_metrics(oidn(buffer.mean, buffer.albedo, buffer.normal), reference)
                    frame = frame_tensors(buffer)
                    candidate = candidate_for(denoiser, frame)
                    for block, image in zip(args.blocks, block_images(denoiser, frame, candidate, args.blocks)):
                        ours = image_metrics(image, reference)
                        per_block[block].append((ours["smape"], theirs["smape"], ours["relmse"], theirs["relmse"]))
                means = {}
                for block, rows in per_block.items():
                    ours_s, theirs_s, ours_r, theirs_r = np.asarray(rows).T
                    means[block] = (paired_ratio(ours_s, theirs_s).geometric_mean,
                                    paired_ratio(ours_r, theirs_r).geometric_mean)
                for block, mean in means.items():
                    cells.setdefault((spp, block), []).append(mean)
                print(f"| {scene.name} | {spp} | " + " | ".join(f"{s:.3f} / {r:.3f}" for s, r in means.values()) + " |",
                      flush=True)
    print("\n| block | " + " | ".join(f"{spp} spp: SMAPE (≤ OIDN) / relMSE (≤ OIDN)" for spp in args.spp)
          + " | mean of the medians |\n|---:|" + "---|" * len(args.spp) + "---:|")
    for block in args.blocks:
        medians, row = [], []
        for spp in args.spp:
            s, r = np.asarray(cells[(spp, block)]).T
            medians += [np.median(s), np.median(r)]
            row.append(f"{np.median(s):.4f} ({(s <= 1).sum()} of {s.size}) / {np.median(r):.4f} ({(r <= 1).sum()} of {r.size})")
        print(f"| {block} | " + " | ".join(row) + f" | {np.mean(medians):.4f} |")


if __name__ == "__main__":
    main()
