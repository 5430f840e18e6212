"""What does exposure normalisation change on typical scenes? (docs/models.md, "Exposure")

Per development scene, as written, against its committed reference: the shipped networks with
the exposure (models.exposure: every image moved to EXPOSURE_KEY) and without it (s = 1, the
networks read the scene's own units, as before). Identical samples in both arms: a uniform
16-spp iteration (denoiser and error network on the same buffer) and the adaptive loop 16 → 128 spp
(error allocator, same seed; its samples differ once an allocation does).

    python -m bench.experiments.exposure_ab [--only SCENE ...] [--loop-spp 128] [--seeds 1]
"""
from __future__ import annotations

import argparse
import math
from contextlib import contextmanager
from typing import Iterator

import numpy as np
import torch

from bench.common import image_metrics
from bench.dev_references import DEFAULT_REFERENCE_DIR, dev_scenes, load_reference
from models.exposure import Exposure, exposure_metric
from models.pretrained import Networks, load_networks
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec
from service.loop.tensors import nchw


@contextmanager
def exposure_off() -> Iterator[None]:
    """Every Exposure.of call answers s = 1: the range [0, ∞] holds every image."""
    of = Exposure.of   # the plain function behind the staticmethod
    saved = of.__defaults__
    of.__defaults__ = (0.0, math.inf)
    try:
        yield
    finally:
        of.__defaults__ = saved


def last_record(scene, networks: Networks, spp_first: int, iterations: int, allocator: str, seed: int = 0):
    spec = LoopSpec(scene=str(scene.path), spp_first=spp_first, max_iterations=iterations, allocator=allocator, seed=seed)
    return list(RenderLoop(spec, networks).run())[-1]


def measure(scene, networks: Networks, reference: np.ndarray, iterations: int, seeds: int) -> dict[str, float]:
    uniform = last_record(scene, networks, 16, 1, "uniform")
    m16 = image_metrics(uniform.denoised[0], reference)
    loops = [image_metrics(last_record(scene, networks, 16, iterations, "error", seed).denoised[0], reference)
             for seed in range(seeds)]
    return {"smape16": m16["smape"], "relmse16": m16["relmse"], "error16": float(uniform.error[0].mean()),
            "smape_loop": float(np.mean([m["smape"] for m in loops])),
            "relmse_loop": float(np.mean([m["relmse"] for m in loops])),
            "E": float(exposure_metric(nchw(uniform.buffers[0].mean))[0])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", default=None)
    parser.add_argument("--loop-spp", type=int, default=128)
    parser.add_argument("--seeds", type=int, default=1, help="loop runs per arm (their SMAPE averaged)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    networks = load_networks()
    iterations = int(round(math.log2(args.loop_spp / 16))) + 1
    print(f"| scene | E | SMAPE 16 off → on | relMSE 16 off → on | predicted error 16 off → on "
          f"| loop {args.loop_spp} SMAPE off → on | loop relMSE off → on |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    ratios: dict[str, list[float]] = {"smape16": [], "relmse16": [], "smape_loop": [], "relmse_loop": []}
    for scene in dev_scenes(args.only):
        if scene.frames != 1:
            continue
        reference, _ = load_reference(DEFAULT_REFERENCE_DIR, scene)
        with exposure_off():
            off = measure(scene, networks, reference, iterations, args.seeds)
        on = measure(scene, networks, reference, iterations, args.seeds)
        for key in ratios:
            ratios[key].append(on[key] / off[key])
        pairs = " | ".join(f"{off[k]:.4g} → {on[k]:.4g}" for k in ("smape16", "relmse16", "error16", "smape_loop", "relmse_loop"))
        print(f"| {scene.name} | {on['E']:.3f} | {pairs} |", flush=True)
    print("geometric mean on ÷ off: " + ", ".join(f"{k} {math.exp(np.mean(np.log(v))):.4f}" for k, v in ratios.items()))


if __name__ == "__main__":
    main()
