"""How well can any error network rank the pixels of one image? (docs/error-network.md, "How
much of a pixel's error can be predicted")

Issue 14 asks for a per-pixel Spearman of 0.7 between predicted and true SMAPE. The true map of
one render is the scene's repeatable error (where the denoiser struggles) plus that render's own
leftover noise, and the second part changes with the seed. Per scene, K renders that differ only
in their seed are denoised by the shipped denoiser; for each render k:

- repeatable ranking: Spearman of the mean of the other K − 1 true maps against map k — what a
  predictor that knew the scene's expected error perfectly (estimated from K − 1 renders, so a
  little low) would score against this one render;
- two renders: Spearman of two single true maps (k, k + 1); under additive noise, ρ(∞) =
  √ρ(two) estimates the first figure with infinitely many renders;
- the shipped error network's prediction for render k, zeroed where every sample agreed as the
  loop does (service.loop.loop.converged_error), against map k (what the calibration report
  measures), and against the mean of the others (how well it ranks the repeatable part).

A predictor reads the render's own inputs, so it can see part of that render's noise (a firefly
in the samples): the figures bound predictors of the expected error, not every predictor.

    python -m bench.experiments.error_ceiling [--suite val|dev] [--spp 16] [--renders 8]
"""
from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from bench.common import denoise_and_predict, load_bench_networks, pinned_torch_threads, true_error_map
from bench.dev_references import SUITES, dev_scenes, load_reference
from bench.quality_measures import block_means, spearman
from bench.suite_quality import uniform_render
from models.pretrained import Networks
from service.loop.loop import converged_error
from service.loop.tensors import frame_tensors, to_image

RANKING_BLOCK = 8   # the calibration report's tile size
FIRST_SEED = 100    # away from the suite report's seed, so these renders are new ones


def leave_one_out_spearman(maps: np.ndarray, block: int = 1) -> float:
    """(K, H, W) maps of one scene → mean over k of Spearman(mean of the others, map k), on
    block×block tile means when block > 1."""
    k = len(maps)
    if k < 2:
        raise ValueError("leave-one-out needs at least two maps")
    total = maps.sum(0)
    tiled = (lambda x: block_means(x, block)) if block > 1 else (lambda x: x)
    return float(np.mean([spearman(tiled((total - m) / (k - 1)), tiled(m)) for m in maps]))


def pairwise_spearman(maps: np.ndarray, block: int = 1) -> float:
    """Mean Spearman of consecutive single maps (k, k + 1): two independent renders' agreement."""
    tiled = (lambda x: block_means(x, block)) if block > 1 else (lambda x: x)
    return float(np.mean([spearman(tiled(a), tiled(b)) for a, b in zip(maps, maps[1:])]))


def infinite_render_estimate(two_render: float) -> float:
    """ρ(∞) = √ρ(two): with map = expected + independent noise of variance ratio r, two single maps
    correlate as 1/(1 + r) and the expected map with one of them as 1/√(1 + r)."""
    return math.sqrt(two_render) if two_render > 0 else float("nan")


def scene_maps(scene, reference: np.ndarray, networks: Networks, spp: int, renders: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """(true SMAPE maps, predicted maps as the loop uses them), each (renders, H, W), of `renders`
    seeds at `spp`."""
    denoiser, error_network = networks.denoiser, networks.error_predictor
    true, predicted = [], []
    for k in range(renders):
        buffer = uniform_render(scene, spp, networks, seed=FIRST_SEED + k).buffers[0]
        frame = frame_tensors(buffer)
        _, denoised, error = denoise_and_predict(denoiser, error_network, [frame], 0)
        true.append(true_error_map(to_image(denoised), reference))
        predicted.append(converged_error(buffer.converged(), to_image(error)))
    return np.stack(true), np.stack(predicted)


def ranking_row(true: np.ndarray, predicted: np.ndarray, block: int = 1) -> dict[str, float]:
    """One scene's figures (see the module text), per pixel or on tiles."""
    tiled = (lambda x: block_means(x, block)) if block > 1 else (lambda x: x)
    k = len(true)
    others = [(true.sum(0) - true[i]) / (k - 1) for i in range(k)]
    two = pairwise_spearman(true, block)
    return {
        "repeatable": leave_one_out_spearman(true, block),
        "two_renders": two,
        "infinite": infinite_render_estimate(two),
        "network": float(np.mean([spearman(tiled(p), tiled(t)) for p, t in zip(predicted, true)])),
        "network_vs_repeatable": float(np.mean([spearman(tiled(p), tiled(o)) for p, o in zip(predicted, others)])),
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--renders", type=int, default=8)
    parser.add_argument("--weights", default=None, help="folder of denoiser.pt and error_predictor.pt (default: shipped)")
    args = parser.parse_args()
    nets = load_bench_networks(args.weights)
    columns = ("repeatable", "two_renders", "infinite", "network", "network_vs_repeatable")
    print(f"{args.renders} renders per scene at {args.spp} spp. Per pixel | on {RANKING_BLOCK}×{RANKING_BLOCK} tiles: "
          "repeatable (mean of K − 1 others vs one) / two renders / √two (∞ renders) / network vs its render / "
          "network vs the mean of the others\n\n| scene | " + " | ".join(columns) + " | tiles: " + " | ".join(columns)
          + " |\n|---|" + "---:|" * (2 * len(columns)))
    rows: list[tuple[dict[str, float], dict[str, float]]] = []
    with pinned_torch_threads(2), torch.no_grad():
        for scene in dev_scenes(None, SUITES[args.suite].root):
            reference, _ = load_reference(SUITES[args.suite].references, scene, None if scene.frames == 1 else 0)
            true, predicted = scene_maps(scene, reference, nets.networks, args.spp, args.renders)
            pixel, tile = ranking_row(true, predicted), ranking_row(true, predicted, RANKING_BLOCK)
            rows.append((pixel, tile))
            print(f"| {scene.name} | " + " | ".join(f"{pixel[c]:.2f}" for c in columns) + " | "
                  + " | ".join(f"{tile[c]:.2f}" for c in columns) + " |", flush=True)
    print("| **median** | " + " | ".join(f"**{np.nanmedian([p[c] for p, _ in rows]):.2f}**" for c in columns) + " | "
          + " | ".join(f"**{np.nanmedian([t[c] for _, t in rows]):.2f}**" for c in columns) + " |")


if __name__ == "__main__":
    main()
