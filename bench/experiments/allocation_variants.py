"""Which allocator step limits error-driven sampling? (docs/error-network.md, "Allocation")

The loop (16 → 128 spp, 4 iterations, seed 1 or --seed) with one allocator setting changed at a time,
driven either by the shipped error network or by the denoised image's true error map
(bench.loop_run.TrueErrorMap); each figure is SMAPE at 128 spp ÷ uniform (b)'s with the same
denoiser. The variants patch `service.loop.loop.allocate_samples`, `allocate.error_weights` and
`allocate.ERROR_GAIN_EXPONENT` for the duration of one loop: an experiment, not a product setting.

    python -m bench.experiments.allocation_variants [--suite val|dev] [--map true|predicted] [--seed S]
"""
from __future__ import annotations

import argparse
from contextlib import contextmanager

import numpy as np

import service.loop.allocate as allocate
import service.loop.loop as loop
from bench.common import image_metrics, load_bench_networks, pinned_torch_threads
from bench.dev_references import SUITES, dev_scenes, load_reference
from bench.loop_run import TrueErrorMap
from models.pretrained import Networks
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec

# name → (error exponent, allocate_samples keyword overrides, the equal-gain rule's β — None: the
# paper's new samples ∝ error, the shipped rule).
SHIPPED_GAIN = allocate.ERROR_GAIN_EXPONENT
VARIANTS: dict[str, tuple[float, dict, float | None]] = {
    "shipped": (1.0, {}, SHIPPED_GAIN),
    "clamp 95": (1.0, {"clamp_percentile": 95.0}, SHIPPED_GAIN),
    "clamp 99.5": (1.0, {"clamp_percentile": 99.5}, SHIPPED_GAIN),
    "no clamp": (1.0, {"clamp_percentile": None}, SHIPPED_GAIN),
    "error²": (2.0, {}, SHIPPED_GAIN),
    "√error": (0.5, {}, SHIPPED_GAIN),
    "no dilation": (1.0, {"dilate_radius": 0}, SHIPPED_GAIN),
    "dilation 3": (1.0, {"dilate_radius": 3}, SHIPPED_GAIN),
    "floor 1 %": (1.0, {"floor_fraction": 0.01}, SHIPPED_GAIN),
    "floor 20 %": (1.0, {"floor_fraction": 0.2}, SHIPPED_GAIN),
    "equal gain β ½": (1.0, {}, 0.5),
    "equal gain β ½, no dilation": (1.0, {"dilate_radius": 0}, 0.5),
    "equal gain β ¼": (1.0, {}, 0.25),
}


@contextmanager
def allocator_variant(exponent: float, overrides: dict, gain: float | None = SHIPPED_GAIN):
    """The loop's allocation with one variant in place, the product's restored after: the error
    map raised to `exponent`, allocate_samples' settings overridden, the equal-gain rule's β."""
    weights, samples, shipped_gain = allocate.error_weights, loop.allocate_samples, allocate.ERROR_GAIN_EXPONENT
    allocate.error_weights = lambda error, *args: weights(error ** exponent, *args)
    loop.allocate_samples = lambda w, budget, **kw: samples(w, budget, **{**kw, **overrides})
    allocate.ERROR_GAIN_EXPONENT = gain
    try:
        yield
    finally:
        allocate.error_weights, loop.allocate_samples = weights, samples
        allocate.ERROR_GAIN_EXPONENT = shipped_gain


def final_smape(scene_path: str, networks: Networks, allocator: str, reference: np.ndarray, seed: int = 1) -> float:
    spec = LoopSpec(scene=scene_path, spp_first=16, max_iterations=4, allocator=allocator, seed=seed)
    return image_metrics(list(RenderLoop(spec, networks).run())[-1].denoised[0], reference)["smape"]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--map", choices=("true", "predicted"), default="predicted")
    parser.add_argument("--seed", type=int, default=1, help="the loops' seed (default 1)")
    args = parser.parse_args()
    nets = load_bench_networks(None)
    print("| scene | " + " | ".join(VARIANTS) + " |\n|---|" + "---:|" * len(VARIANTS))
    with pinned_torch_threads(2):
        for scene in dev_scenes(None, SUITES[args.suite].root):
            if scene.frames > 1:
                continue
            reference, _ = load_reference(SUITES[args.suite].references, scene, None)
            uniform = final_smape(str(scene.path), nets.networks, "uniform", reference, args.seed)
            error_map = TrueErrorMap(reference) if args.map == "true" else nets.networks.error_predictor
            networks = Networks(nets.networks.denoiser, error_map)
            ratios = []
            for exponent, overrides, gain in VARIANTS.values():
                with allocator_variant(exponent, overrides, gain):
                    ratios.append(final_smape(str(scene.path), networks, "error", reference, args.seed) / uniform)
            print(f"| {scene.name} | " + " | ".join(f"{r:.3f}" for r in ratios) + " |", flush=True)


if __name__ == "__main__":
    main()
