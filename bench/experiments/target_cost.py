"""What a training scene's target costs: a clean reference against a Noise2Noise target
(docs/noisy-targets.md). Per procedural training scene, in one process: the wall time of one
render at the inputs' sample count (the uniform 16 → 128 levels plus the adaptive branch's 48:
≈ 176 spp as one pass), of a clean reference and of a noisy target.

    python -m bench.experiments.target_cost [--scenes 10] [--size 128] [--reference-spp 512] [--target-spp 64]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from service.dataset.build import ADAPTIVE_ITEMS, UNIFORM_STEPS
from service.dataset.procedural import sample_spec, scene_dict
from service.dataset.splits import scene_seeds
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.runtime import mitsuba

# the uniform levels' samples, then each adaptive step adds as many as the 16-spp buffer holds
INPUT_SPP = sum(added for _, added in UNIFORM_STEPS) + sum(16 * 2 ** i for i in range(len(ADAPTIVE_ITEMS)))


def render_seconds(scene, size: int, spp: int, seed: int = 1) -> float:
    """Wall time of one uniform `spp` render of a loaded scene at size²."""
    buffer = FrameBuffer.empty(size, size)
    started = time.perf_counter()
    render_samples(scene, np.full((size, size), spp), buffer, seed=seed)
    return time.perf_counter() - started


def scene_costs(scenes: int, size: int, spp_counts: tuple[int, ...], seed: int = 0) -> dict[int, float]:
    """Summed wall seconds per sample count over the first `scenes` training scenes of `seed`."""
    mi = mitsuba()
    totals = dict.fromkeys(spp_counts, 0.0)
    for scene_seed in scene_seeds("train", scenes, seed):
        scene = mi.load_dict(scene_dict(sample_spec(scene_seed), size=size, frame=0))
        for spp in spp_counts:
            totals[spp] += render_seconds(scene, size, spp)
    return totals


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scenes", type=int, default=10)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--reference-spp", type=int, default=512)
    parser.add_argument("--target-spp", type=int, default=64)
    args = parser.parse_args()
    costs = scene_costs(args.scenes, args.size, (INPUT_SPP, args.reference_spp, args.target_spp))
    per = {spp: seconds / args.scenes for spp, seconds in costs.items()}
    clean, noisy = per[INPUT_SPP] + per[args.reference_spp], per[INPUT_SPP] + per[args.target_spp]
    print(f"per scene at {args.size}²: inputs ({INPUT_SPP} spp) {per[INPUT_SPP]:.2f} s, "
          f"reference ({args.reference_spp} spp) {per[args.reference_spp]:.2f} s, "
          f"target ({args.target_spp} spp) {per[args.target_spp]:.2f} s; "
          f"scene with a clean reference {clean:.2f} s, with a noisy target {noisy:.2f} s ({clean / noisy:.2f}× cheaper)")


if __name__ == "__main__":
    main()
