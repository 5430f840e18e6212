"""Does the disagreement of the two denoisers rank the error the error network misses?
(docs/error-network.md, "Tried and not shipped: the kernels' disagreement with OIDN")

The shipped denoiser blends its kernels' image k with OIDN's image o. Where the two disagree,
at least one is wrong: the disagreement D = mean_c |k − o| / (|k| + |o| + ε), box-filtered over
5×5, is an uncertainty signal, like an ensemble's spread. The error network ranks worst on fog
and lamp-shade scenes (docs/error-network.md, "How much of a pixel's error can be predicted").
The variant multiplies the network's map by (D / mean D)^γ and rescales it to the network's
image mean. The mean stays the network's, so `--target-error` is unchanged; only the ranking,
and with it the allocation, moves.

    python -m bench.experiments.disagreement_map rank [--suite val] [--spp 16 64]   # Spearman, per pixel / 8×8 tiles
    python -m bench.experiments.disagreement_map loop [--suite val] [--gamma 0.25 0.5] [--seed 1]   # (d) ÷ (b) at 128 spp
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from bench.common import load_bench_networks, pinned_torch_threads, true_error_map
from bench.dev_references import SUITES, dev_scenes, load_reference
from bench.experiments.allocation_variants import final_smape, uniform_baselines
from bench.experiments.gate_bound import kernels_and_candidate
from bench.quality_measures import block_means, spearman
from bench.suite_quality import uniform_render
from models.denoiser import Denoiser
from models.error_predictor import reads_disagreement
from models.kernel_disagreement import kernel_disagreement
from models.pretrained import Networks
from service.loop.tensors import frame_tensors, to_image

TILE = 8         # tile size of the tile Spearman (the allocator's scale after dilation)


def modulate(predicted: torch.Tensor, dis: torch.Tensor, gamma: float) -> torch.Tensor:
    """predicted × (dis / mean dis)^γ, rescaled so its mean is the prediction's own."""
    if gamma == 0:
        return predicted
    weight = (dis / dis.mean().clamp_min(1e-12)) ** gamma
    out = predicted * weight
    return out * (predicted.mean() / out.mean().clamp_min(1e-12))


class ModulatedErrorMap(torch.nn.Module):
    """The loop's error network with its map modulated by the disagreement (an experiment)."""

    def __init__(self, error_predictor: torch.nn.Module, denoiser: Denoiser, gamma: float):
        super().__init__()
        self.error_predictor, self.denoiser, self.gamma = error_predictor, denoiser, gamma

    def forward(self, frame, denoised: torch.Tensor) -> torch.Tensor:
        reads = reads_disagreement(self.error_predictor)
        if self.gamma == 0 and not reads:
            return self.error_predictor(frame, denoised)
        _, kernels, candidate = kernels_and_candidate(self.denoiser, frame)
        dis = kernel_disagreement(kernels, candidate)
        predicted = self.error_predictor(frame, denoised, dis) if reads else self.error_predictor(frame, denoised)
        return modulate(predicted, dis, self.gamma)


def spearman_pair(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Spearman per pixel and of the 8×8 tile means."""
    return spearman(a, b), spearman(block_means(a, TILE), block_means(b, TILE))


def rank(args, nets) -> None:
    names = ["network", "disagreement", "network × D^½", "network × D"]
    print("Spearman with the true SMAPE map, per pixel / 8×8 tiles\n\n| scene | spp | " + " | ".join(names) + " |\n"
          "|---|---:|" + "---:|" * len(names))
    rows = []
    denoiser = nets.networks.denoiser
    with pinned_torch_threads(2), torch.no_grad():
        for scene in dev_scenes(None, SUITES[args.suite].root):
            reference, _ = load_reference(SUITES[args.suite].references, scene, None if scene.frames == 1 else 0)
            for spp in args.spp:
                frame = frame_tensors(uniform_render(scene, spp, nets.networks).buffers[0])
                output, kernels, candidate = kernels_and_candidate(denoiser, frame)
                true = true_error_map(to_image(output), reference)
                dis = kernel_disagreement(kernels, candidate)
                predicted = nets.networks.error_predictor(frame, output, dis)
                maps = [predicted, dis, modulate(predicted, dis, 0.5), modulate(predicted, dis, 1.0)]
                row = [spearman_pair(to_image(m).squeeze(), true) for m in maps]
                rows.append(row)
                print(f"| {scene.name} | {spp} | " + " | ".join(f"{a:.2f} / {b:.2f}" for a, b in row) + " |", flush=True)
    medians = np.median(np.array(rows), axis=0)
    print("| **median** | | " + " | ".join(f"{a:.2f} / {b:.2f}" for a, b in medians) + " |")


def loop(args, nets) -> None:
    print("SMAPE at 128 spp ÷ uniform (b)'s, same denoiser, seed", args.seed, "\n\n| scene | shipped | " +
          " | ".join(f"γ = {g:g}" for g in args.gamma) + " |\n|---|---:|" + "---:|" * len(args.gamma))
    rows = []
    denoiser = nets.networks.denoiser
    with pinned_torch_threads(2):
        for scene, reference, uniform in uniform_baselines(args.suite, nets.networks, args.seed):
            row = []
            for gamma in [0.0, *args.gamma]:
                networks = Networks(denoiser, ModulatedErrorMap(nets.networks.error_predictor, denoiser, gamma))
                row.append(final_smape(str(scene.path), networks, "error", reference, args.seed) / uniform)
            rows.append(row)
            print(f"| {scene.name} | " + " | ".join(f"{r:.3f}" for r in row) + " |", flush=True)
    print("| **mean** | " + " | ".join(f"{r:.3f}" for r in np.mean(rows, axis=0)) + " |")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("what", choices=("rank", "loop"))
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--spp", type=int, nargs="+", default=[16, 64])
    parser.add_argument("--gamma", type=float, nargs="+", default=[0.25, 0.5])
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    nets = load_bench_networks(None)
    (rank if args.what == "rank" else loop)(args, nets)


if __name__ == "__main__":
    main()
