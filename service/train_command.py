"""`renderloop train --data DIR --stage ... -o models/weights/`: arguments → TrainConfig → the trainer."""
from __future__ import annotations

import shlex
import sys
from pathlib import Path

from service.training.trainer import STAGES, TrainConfig, TrainConfigError, run_training


def add_parser(sub) -> None:
    p = sub.add_parser("train", help="train the denoiser and/or the error predictor on a built data set")
    p.add_argument("--data", type=Path, required=True, help="data set folder (renderloop dataset -o ...)")
    p.add_argument("--stage", choices=STAGES, default="all",
                   help="single|multiscale|temporal|lambda: one paper stage (from --init or the previous "
                        "stage's file); staged: all four then the error network; denoiser: end to end; "
                        "error: the error network; all: denoiser then error (default)")
    p.add_argument("-o", "--out", type=Path, default=Path("models/weights"))
    p.add_argument("--steps", type=int, default=1500, help="optimiser steps per stage (default 1500)")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--crop", type=int, default=48)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--val-every", type=int, default=150)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=None, help="denoiser feature width (default: model default)")
    p.add_argument("--spatial-blocks", type=int, default=None,
                   help="residual blocks of the denoiser's spatial extractor (default: model default)")
    p.add_argument("--symmetric-fraction", type=float, default=0.5,
                   help="first fraction of denoiser steps trained at λ = 1 before λ is randomised (default 0.5)")
    p.add_argument("--init", type=Path, default=None, help="start the denoiser from this checkpoint's weights")
    p.add_argument("--resume", action="store_true", help="continue from OUT/.train_<stage>.pt")
    p.add_argument("--device", default=None, help="cpu | cuda (default: cuda when available)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(handler=run_train)


def run_train(args) -> int:
    config = TrainConfig(
        data=args.data, out=args.out, stage=args.stage, steps=args.steps, batch=args.batch, crop=args.crop,
        lr=args.lr, val_every=args.val_every, seed=args.seed, width=args.width, spatial_blocks=args.spatial_blocks,
        symmetric_fraction=args.symmetric_fraction, init=args.init, resume=args.resume, device=args.device,
        quiet=args.quiet, command_line="renderloop " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
    )
    try:
        lines = run_training(config)
    except TrainConfigError as exc:
        print(f"renderloop train: error: {exc}", file=sys.stderr)
        return 2
    print("\n".join(lines))
    return 0
