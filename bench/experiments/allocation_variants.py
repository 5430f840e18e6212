"""Which allocator step limits error-driven sampling? (docs/error-network.md, "Allocation")

The loop (16 → 128 spp, 4 iterations, seed 1) with one allocator setting changed at a time,
driven either by the shipped error network or by the denoised image's true error map
(bench.loop_run.TrueErrorMap); each figure is SMAPE at 128 spp ÷ uniform (b)'s with the same
denoiser. The variants patch `service.loop.loop.allocate_samples` / `allocate.error_weights` for
the duration of one loop: an experiment, not a product setting.

    python -m bench.experiments.allocation_variants [--suite val|dev] [--map true|predicted]
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

# name → (error exponent, allocate_samples keyword overrides)
VARIANTS: dict[str, tuple[float, dict]] = {
    "shipped": (1.0, {}),
    "clamp 95": (1.0, {"clamp_percentile": 95.0}),
    "clamp 99.5": (1.0, {"clamp_percentile": 99.5}),
    "no clamp": (1.0, {"clamp_percentile": None}),
    "error²": (2.0, {}),
    "√error": (0.5, {}),
    "no dilation": (1.0, {"dilate_radius": 0}),
    "dilation 3": (1.0, {"dilate_radius": 3}),
    "floor 1 %": (1.0, {"floor_fraction": 0.01}),
    "floor 20 %": (1.0, {"floor_fraction": 0.2}),
}


@contextmanager
def allocator_variant(exponent: float, overrides: dict):
    weights, samples = allocate.error_weights, loop.allocate_samples
    allocate.error_weights = lambda error: weights(error) ** exponent
    loop.allocate_samples = lambda w, budget, **kw: samples(w, budget, **{**kw, **overrides})
    try:
        yield
    finally:
        allocate.error_weights, loop.allocate_samples = weights, samples


def final_smape(scene_path: str, networks: Networks, allocator: str, reference: np.ndarray) -> float:
    spec = LoopSpec(scene=scene_path, spp_first=16, max_iterations=4, allocator=allocator, seed=1)
    return image_metrics(list(RenderLoop(spec, networks).run())[-1].denoised[0], reference)["smape"]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--map", choices=("true", "predicted"), default="predicted")
    args = parser.parse_args()
    nets = load_bench_networks(None)
    print("| scene | " + " | ".join(VARIANTS) + " |\n|---|" + "---:|" * len(VARIANTS))
    with pinned_torch_threads(2):
        for scene in dev_scenes(None, SUITES[args.suite].root):
            if scene.frames > 1:
                continue
            reference, _ = load_reference(SUITES[args.suite].references, scene, None)
            uniform = final_smape(str(scene.path), nets.networks, "uniform", reference)
            error_map = TrueErrorMap(reference) if args.map == "true" else nets.networks.error_predictor
            networks = Networks(nets.networks.denoiser, error_map)
            ratios = []
            for exponent, overrides in VARIANTS.values():
                with allocator_variant(exponent, overrides):
                    ratios.append(final_smape(str(scene.path), networks, "error", reference) / uniform)
            print(f"| {scene.name} | " + " | ".join(f"{r:.3f}" for r in ratios) + " |", flush=True)


if __name__ == "__main__":
    main()
