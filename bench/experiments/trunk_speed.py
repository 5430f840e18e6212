"""What the U-Net trunk costs at inference against the paper's per-level trunk
(docs/unet-trunk.md): one frame through the single-frame multi-scale denoiser, without its OIDN
call, untrained weights (speed does not depend on them), median of the repeats after a warm-up.

    python -m bench.experiments.trunk_speed [--size 512] [--threads 2] [--repeats 5]
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import torch

from bench.common import pinned_torch_threads
from models.denoiser import TRUNKS, Denoiser, DenoiserConfig
from models.frames import FrameTensors

SHIPPED_SHAPE = DenoiserConfig(width=16, temporal=False)   # the shipped denoiser's, without its candidate


def random_frame(size: int, seed: int = 0) -> FrameTensors:
    g = torch.Generator().manual_seed(seed)
    rand = lambda c: torch.rand(1, c, size, size, generator=g)   # noqa: E731
    return FrameTensors(color=rand(3) * 2, variance=rand(3) * 0.1, albedo=rand(3) * 0.8 + 0.1,
                        normal=rand(3) * 2 - 1, depth=rand(1) + 1, motion=None)


@torch.inference_mode()
def median_seconds(config: DenoiserConfig, frame: FrameTensors, repeats: int) -> float:
    denoiser = Denoiser(config).eval()
    denoiser([frame], 0, 1.0)                                      # warm-up
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        denoiser([frame], 0, 1.0)
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    frame = random_frame(args.size)
    with pinned_torch_threads(args.threads):
        seconds = {trunk: median_seconds(dataclasses.replace(SHIPPED_SHAPE, trunk=trunk), frame, args.repeats)
                   for trunk in TRUNKS}
    print(", ".join(f"{trunk} {s * 1000:.0f} ms" for trunk, s in seconds.items())
          + f" at {args.size}², {args.threads} threads; unet ÷ levels {seconds['unet'] / seconds['levels']:.2f}×")


if __name__ == "__main__":
    main()
