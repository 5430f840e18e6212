"""Which error network allocates better? The loop (16 → 128 spp, 4 iterations) on each still
scene, driven by each named folder's error network beside one denoiser, against the same
uniform (b) baseline (docs/error-network.md).

Each figure is the loop's SMAPE at 128 spp ÷ uniform (b)'s with the same denoiser; the
denoiser is the first folder's, so only the error networks differ.

    python -m bench.experiments.error_network_loop DIR [DIR ...] [--suite val] [--seed 1]
"""
from __future__ import annotations

import argparse

import numpy as np

from bench.common import load_bench_networks, pinned_torch_threads
from bench.dev_references import SUITES
from bench.experiments.allocation_variants import final_smape, uniform_baselines
from models.pretrained import Networks


def loop_ratios(folders: list[str], suite: str, seed: int) -> list[tuple[str, list[float]]]:
    """Per still scene: each folder's error network's loop SMAPE ÷ uniform (b)'s."""
    loaded = [load_bench_networks(folder).networks for folder in folders]
    denoiser = loaded[0].denoiser
    rows = []
    for scene, reference, uniform in uniform_baselines(suite, loaded[0], seed):
        ratios = [final_smape(str(scene.path), Networks(denoiser, nets.error_predictor), "error", reference, seed)
                  / uniform for nets in loaded]
        rows.append((scene.name, ratios))
        print(f"| {scene.name} | " + " | ".join(f"{r:.3f}" for r in ratios) + " |", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("folders", nargs="+", help="weights folders (error_predictor.pt; the first one's denoiser)")
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    print(f"SMAPE at 128 spp ÷ uniform (b)'s, seed {args.seed}\n\n| scene | " + " | ".join(args.folders) + " |\n|---|"
          + "---:|" * len(args.folders))
    with pinned_torch_threads(2):
        rows = loop_ratios(args.folders, args.suite, args.seed)
    print("| **mean** | " + " | ".join(f"{r:.3f}" for r in np.mean([r for _, r in rows], axis=0)) + " |")


if __name__ == "__main__":
    main()
