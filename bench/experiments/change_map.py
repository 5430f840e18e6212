"""Does the denoised image's change between iterations, kept per pixel, sharpen the error map?
(docs/error-network.md, "Tried and not shipped: the change between iterations, per pixel")

The loop already measures how far the denoised image moved since the previous iteration, as one
number C that calibrates the error map's mean (service/loop/change_calibration.py). Kept per
pixel — the SMAPE map between the two images, box-filtered over 5×5 — it is a reference-free sign
of where the image is still unsettled. The variant multiplies the network's map by
(Cᵢ / mean C)^γ and rescales it to the map's own mean (`disagreement_map.modulate`), from the
second iteration on. The mean, and with it `--target-error`, stays the shipped loop's; what
moves is the ranking and, through the allocator, where the next samples go. That feeds back: a
pixel that was given more samples also moves more.

Per scene and seed: the shipped loop and one loop per γ (16 → 128 spp, error allocator), each
scored at its last iteration: its SMAPE ÷ the shipped loop's, and the per-pixel Spearman of its
own map against its own true error (the calibration report's figure).

    python -m bench.experiments.change_map [--suite val|dev] [--gamma 0.25 0.5 1] [--seeds 1 2 3 4]
"""
from __future__ import annotations

import argparse
from typing import Sequence

import numpy as np
import torch
from scipy.ndimage import uniform_filter

from bench.common import image_metrics, load_bench_networks, pinned_torch_threads, true_error_map
from bench.dev_references import SUITES, still_scenes
from bench.experiments.disagreement_map import modulate
from bench.quality_measures import spearman
from models.pretrained import Networks
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec

CHANGE_BOX = 5   # pixels: the denoiser spreads a pixel's samples over its neighbours
ITERATIONS = 4   # 16 → 128 spp, as the loop benchmark's methods run


def change_shaped(error: np.ndarray, previous: np.ndarray, current: np.ndarray, gamma: float) -> np.ndarray:
    """The (H, W) error map × (Cᵢ / mean C)^γ at its own mean, Cᵢ the box-filtered per-pixel SMAPE
    between the two images."""
    change = uniform_filter(true_error_map(current, previous), CHANGE_BOX)
    if not change.mean() > 0:   # the same image twice: no sign of where it is unsettled
        return error
    shaped = modulate(torch.from_numpy(np.asarray(error, np.float64)), torch.from_numpy(change.astype(np.float64)), gamma)
    return shaped.numpy().astype(np.float32)


class ChangeShapedLoop(RenderLoop):
    """The loop with its error map shaped by the per-pixel change wherever it measures a change."""

    def __init__(self, spec: LoopSpec, networks: Networks, gamma: float):
        super().__init__(spec, networks)
        self.gamma = gamma

    def _calibrate_by_change(self, previous, previous_lam) -> None:
        super()._calibrate_by_change(previous, previous_lam)
        if previous_lam is None or not np.array_equal(previous_lam, self.state.lam_map):
            return
        for f, (image, samples) in previous.items():
            if samples is not None and 2 * samples == self._denoised_samples[f]:   # the image before
                self.state.error_maps[f] = change_shaped(self.state.error_maps[f], image, self._denoised[f], self.gamma)


def last_scores(loop: RenderLoop, reference: np.ndarray) -> tuple[float, float]:
    """SMAPE of the loop's last denoised image and the per-pixel Spearman of its error map."""
    last = list(loop.run())[-1]
    return (image_metrics(last.denoised[0], reference)["smape"],
            spearman(last.error[0], true_error_map(last.denoised[0], reference)))


def scene_rows(scene_path: str, reference: np.ndarray, networks: Networks, gammas: Sequence[float],
               seeds: Sequence[int]) -> list[tuple[float, float]]:
    """Per setting (shipped, then each γ): (SMAPE ÷ the shipped loop's, Spearman), means over the seeds."""
    per_seed = []
    for seed in seeds:
        spec = LoopSpec(scene=scene_path, max_iterations=ITERATIONS, allocator="error", seed=seed)
        scores = [last_scores(RenderLoop(spec, networks), reference)]
        scores += [last_scores(ChangeShapedLoop(spec, networks, gamma), reference) for gamma in gammas]
        per_seed.append([(s / scores[0][0], rho) for s, rho in scores])
    return [tuple(float(x) for x in row) for row in np.mean(np.asarray(per_seed), axis=0)]


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--gamma", type=float, nargs="+", default=[0.25, 0.5, 1.0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    parser.add_argument("--weights", default=None, help="folder of denoiser.pt and error_predictor.pt (default: shipped)")
    args = parser.parse_args(argv)
    networks = load_bench_networks(args.weights).networks
    print(f"At 128 spp, means over seeds {args.seeds}: SMAPE ÷ the shipped loop's / per-pixel Spearman of the map\n\n"
          "| scene | shipped | " + " | ".join(f"γ = {g:g}" for g in args.gamma) + " |\n|---|---|" + "---|" * len(args.gamma))
    rows = []
    with pinned_torch_threads(2), torch.no_grad():
        for scene, reference in still_scenes(args.suite):
            row = scene_rows(str(scene.path), reference, networks, args.gamma, args.seeds)
            rows.append(row)
            print(f"| {scene.name} | " + " | ".join(f"{r:.3f} / {rho:.2f}" for r, rho in row) + " |", flush=True)
    medians = np.median(np.asarray(rows), axis=0)
    better = (np.asarray(rows)[:, :, 0] < 1).sum(axis=0)
    print("| **median** | " + " | ".join(f"{r:.3f} / {rho:.2f}" for r, rho in medians) + " |")
    print("| SMAPE below the shipped loop's | — | " + " | ".join(f"{n} of {len(rows)}" for n in better[1:]) + " |")


if __name__ == "__main__":
    main()
