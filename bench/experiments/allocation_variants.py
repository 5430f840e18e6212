"""Which allocator step limits error-driven sampling? (docs/error-network.md, "Allocation")

The loop (16 → 128 spp, 4 iterations, seed 1 or --seed) with one allocator setting changed at a time,
driven either by the shipped error network or by the denoised image's true error map
(bench.loop_run.TrueErrorMap); each figure is SMAPE at 128 spp ÷ uniform (b)'s with the same
denoiser. The variants patch `service.loop.loop.allocate_samples` / `next_counts` and
`allocate.error_weights` for the duration of one loop: an experiment, not a product setting.

    python -m bench.experiments.allocation_variants [--suite val|dev] [--map true|predicted] [--seed S]
"""
from __future__ import annotations

import argparse
from contextlib import contextmanager
from typing import Iterator

import numpy as np

import service.loop.allocate as allocate
import service.loop.loop as loop
from bench.common import image_metrics, load_bench_networks, pinned_torch_threads
from bench.dev_references import SUITES, DevScene, still_scenes
from bench.loop_run import TrueErrorMap
from models.pretrained import Networks
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec

# name → (error exponent, allocate_samples keyword overrides, β of `equal_gain_samples` — None:
# the shipped rule, the paper's new samples ∝ error).
VARIANTS: dict[str, tuple[float, dict, float | None]] = {
    "shipped": (1.0, {}, None),
    "clamp 95": (1.0, {"clamp_percentile": 95.0}, None),
    "clamp 99.5": (1.0, {"clamp_percentile": 99.5}, None),
    "no clamp": (1.0, {"clamp_percentile": None}, None),
    "error²": (2.0, {}, None),
    "√error": (0.5, {}, None),
    "no dilation": (1.0, {"dilate_radius": 0}, None),
    "dilation 3": (1.0, {"dilate_radius": 3}, None),
    "floor 1 %": (1.0, {"floor_fraction": 0.01}, None),
    "floor 20 %": (1.0, {"floor_fraction": 0.2}, None),
    "equal gain β ½": (1.0, {}, 0.5),
    "equal gain β ½, no dilation": (1.0, {"dilate_radius": 0}, 0.5),
    "equal gain β ¼": (1.0, {}, 0.25),
}


def equal_gain_samples(error: np.ndarray, spp: np.ndarray, budget: int, beta: float) -> np.ndarray:
    """New samples per pixel (real-valued, summing to `budget`) that make the error one more
    sample removes equal everywhere, for errors falling as e ∝ n^−β.

    Minimising Σ e_i(n_i) at fixed Σ n_i asks for equal marginal gains β·e_i/n_i, i.e. a total
    n_i = s·(e_i·n_i^β)^(1/(1+β)) measured at the current (e_i, n_i): pixels already past
    their share get nothing, new_i = max(0, total_i − n_i), and s (monotone) is found by
    bisection. The paper's ∝ e_i keeps feeding a pixel however many samples it holds. Measured
    against it, not shipped (docs/error-network.md, "Allocation: what each pixel already has")."""
    e = np.nan_to_num(np.asarray(error, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0).clip(min=0.0)
    n = np.maximum(np.asarray(spp, dtype=np.float64), 1.0)  # a pixel never sampled counts as one
    g = (e * n ** beta) ** (1.0 / (1.0 + beta))
    if budget <= 0 or not (g > 0).any():
        return np.full(e.shape, max(budget, 0) / max(e.size, 1))
    lo, hi = 0.0, (n.max() + budget) / g[g > 0].min()
    for _ in range(100):   # halves [lo, hi] to far below one sample
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if np.maximum(0.0, mid * g - n).sum() > budget else (mid, hi)
    new = np.maximum(0.0, hi * g - n)
    return new * (budget / new.sum())


@contextmanager
def allocator_variant(exponent: float, overrides: dict, gain: float | None = None):
    """The loop's allocation with one variant in place, the product's restored after: the error
    map raised to `exponent`, allocate_samples' settings overridden, and with `gain` the error
    allocator's weights replaced by `equal_gain_samples` (it needs each pixel's count, so the
    loop's `next_counts` is what gets replaced)."""
    weights, samples, counts = allocate.error_weights, loop.allocate_samples, loop.next_counts
    allocate.error_weights = lambda error: weights(error ** exponent)
    loop.allocate_samples = lambda w, budget, **kw: samples(w, budget, **{**kw, **overrides})
    if gain is not None:
        def next_counts(allocator, buffer, predicted_error, budget, seed):
            if allocator != "error":
                return counts(allocator, buffer, predicted_error, budget, seed)
            w = equal_gain_samples(allocate.error_weights(predicted_error), buffer.spp, budget, gain)
            return loop.allocate_samples(w, budget, seed=seed, floor_only=buffer.converged())
        loop.next_counts = next_counts
    try:
        yield
    finally:
        allocate.error_weights, loop.allocate_samples, loop.next_counts = weights, samples, counts


def final_smape(scene_path: str, networks: Networks, allocator: str, reference: np.ndarray, seed: int = 1) -> float:
    spec = LoopSpec(scene=scene_path, spp_first=16, max_iterations=4, allocator=allocator, seed=seed)
    return image_metrics(list(RenderLoop(spec, networks).run())[-1].denoised[0], reference)["smape"]


def uniform_baselines(suite: str, networks: Networks, seed: int) -> Iterator[tuple[DevScene, np.ndarray, float]]:
    """Each still scene of `suite`, its reference, and uniform (b)'s SMAPE at 128 spp: what every
    variant's loop is divided by."""
    for scene, reference in still_scenes(suite):
        yield scene, reference, final_smape(str(scene.path), networks, "uniform", reference, seed)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--map", choices=("true", "predicted"), default="predicted")
    parser.add_argument("--seed", type=int, default=1, help="the loops' seed (default 1)")
    args = parser.parse_args()
    nets = load_bench_networks(None)
    print("| scene | " + " | ".join(VARIANTS) + " |\n|---|" + "---:|" * len(VARIANTS))
    with pinned_torch_threads(2):
        for scene, reference, uniform in uniform_baselines(args.suite, nets.networks, args.seed):
            error_map = TrueErrorMap(reference) if args.map == "true" else nets.networks.error_predictor
            networks = Networks(nets.networks.denoiser, error_map)
            ratios = []
            for exponent, overrides, gain in VARIANTS.values():
                with allocator_variant(exponent, overrides, gain):
                    ratios.append(final_smape(str(scene.path), networks, "error", reference, args.seed) / uniform)
            print(f"| {scene.name} | " + " | ".join(f"{r:.3f}" for r in ratios) + " |", flush=True)


if __name__ == "__main__":
    main()
