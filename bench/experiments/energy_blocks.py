"""Should the samples' energy be restored block by block as well as image-wide? (docs/models.md,
"Energy, block by block"; models/energy.py)

The image-wide factor (`energy_tolerance`) puts back what the denoiser lost wherever it lost it,
spread evenly over the frame; `energy_block` B then restores each B×B block's samples' total
with the same inverse-variance trust. The sweep is bench.experiments.setting_sweep's over
`energy_block` (0 = image-wide only).

    python -m bench.experiments.energy_blocks [--suite val|dev] [--spp 16 64 256] [--blocks 0 32 64]
                                              [--seeds 1 2 3] [--weights DIR]
"""
from __future__ import annotations

import argparse

from bench.common import load_bench_networks
from bench.dev_references import SUITES
from bench.experiments.setting_sweep import sweep


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--spp", type=int, nargs="+", default=[16, 64, 256])
    parser.add_argument("--blocks", type=int, nargs="+", default=[0, 32, 64])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--weights", default=None, help="folder of denoiser.pt and error_predictor.pt (default: shipped)")
    args = parser.parse_args()
    if any(b < 0 for b in args.blocks):
        parser.error("--blocks must be >= 0")
    nets = load_bench_networks(args.weights)
    if nets.networks.denoiser.config.energy_tolerance <= 0:
        parser.error("the weights' config has no energy_tolerance: there is no energy step to refine")
    sweep(nets.networks, args.suite, "energy_block", args.blocks, args.spp, args.seeds)


if __name__ == "__main__":
    main()
