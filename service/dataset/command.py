"""`renderloop dataset`: build (or resume) a procedural training / held-out data set."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from service.dataset.procedural import DATASET_LAYOUTS
from service.dataset.splits import SPLITS

DEFAULT_REFERENCE_SPP = 1024


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register `dataset` on the CLI's subparsers; `args.handler` runs it."""
    p = subparsers.add_parser(
        "dataset",
        help="render procedural scenes into a denoiser training data set",
        description="Render procedural scenes with the project's renderer: noisy inputs at "
                    "16/32/64/128 spp, variance-adaptive inputs, and a high-spp reference per "
                    "frame, as EXR plus manifest.json. Re-running resumes (finished items are skipped).",
    )
    p.add_argument("-o", "--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--scenes", type=int, default=8, metavar="N", help="number of scenes (default 8)")
    p.add_argument("--size", type=int, default=64, metavar="S", help="image width = height in pixels (default 64)")
    p.add_argument("--frames", type=int, default=1, metavar="F",
                   help="frames per scene; > 1 renders a camera path with motion vectors (default 1)")
    p.add_argument("--seed", type=int, default=0, metavar="K", help="data-set seed choosing the scenes (default 0)")
    p.add_argument("--split", choices=SPLITS, default="train",
                   help="seed range to draw scenes from; held-out seeds never occur in train")
    p.add_argument("--reference-spp", type=int, default=DEFAULT_REFERENCE_SPP, metavar="R",
                   help=f"samples per pixel of the reference (default {DEFAULT_REFERENCE_SPP})")
    p.add_argument("--loop-branch", action="store_true",
                   help="also continue each 16-spp buffer with the render loop's own steps (denoise, predict "
                        "error, allocate by it) into loop32/loop64/loop128: what the error network is trained on")
    p.add_argument("--weights", type=Path, metavar="DIR",
                   help="networks that drive --loop-branch (default: the shipped ones)")
    p.add_argument("--layout", choices=DATASET_LAYOUTS, default="mixed",
                   help="scene layout: mixed (each seed draws a room open at the front or open ground, the "
                        "default), or for every scene window: closed rooms lit only by sun and sky through an "
                        "opening; shaded: closed rooms lit only by a tiny, very bright bulb inside an opaque "
                        "lampshade (fireflies)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Build the data set; a bad value prints one line to stderr and returns 2."""
    # Imported here so `renderloop --help` does not pay for Mitsuba start-up.
    from models.checkpoint import CheckpointError
    from models.pretrained import load_networks
    from service.dataset.build import DatasetError, build_dataset

    try:
        networks = load_networks(args.weights) if args.loop_branch else None
        manifest = build_dataset(
            args.out, scenes=args.scenes, size=args.size, frames=args.frames, seed=args.seed,
            split=args.split, reference_spp=args.reference_spp, progress=not args.quiet, loop_networks=networks,
            layout=args.layout,
        )
    except (DatasetError, CheckpointError) as exc:
        print(f"renderloop dataset: error: {exc}", file=sys.stderr)
        return 2
    print(f"data set written: {manifest}")
    return 0
