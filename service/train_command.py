"""`renderloop train --data DIR --stage ... -o DIR`: arguments → TrainConfig → the trainer.
Defaults are TrainConfig's own; the flags are those the recipe uses (scripts/train-weights.sh)."""
from __future__ import annotations

import sys
from pathlib import Path

from service.training.config import STAGES, TrainConfig, TrainConfigError

DEFAULTS = TrainConfig(data=Path("."))


def add_parser(sub) -> None:
    d = DEFAULTS
    p = sub.add_parser("train", help="train the denoiser or the error predictor on built data sets",
                       description="One stage of the recipe (scripts/train-weights.sh, docs/models.md) on the "
                                   "shipped network's configuration.")
    p.add_argument("--data", type=Path, required=True, action="append",
                   help="data set folder (renderloop dataset -o ...); repeat it to train on several together")
    p.add_argument("--stage", choices=STAGES, required=True,
                   help="single: one pyramid level at λ = 1; multiscale: every level and the compositor; temporal: "
                        "the temporal extractor (--temporal); gate: only the OIDN candidate's gate; lambda: only "
                        "the λ directions (writes denoiser.pt with the post-training settings); error: the error "
                        "network of OUT/denoiser.pt")
    p.add_argument("-o", "--out", type=Path, default=d.out, help=f"output folder (default {d.out})")
    p.add_argument("--init", type=Path, default=d.init,
                   help="start from this checkpoint (the previous stage's; --stage error: an error network's, "
                        "its calibration reset)")
    p.add_argument("--steps", type=int, default=d.steps, help=f"optimiser steps (default {d.steps})")
    p.add_argument("--batch", type=int, default=d.batch, help=f"crops per step (default {d.batch})")
    p.add_argument("--crop", type=int, default=d.crop, help=f"crop size in pixels (default {d.crop})")
    p.add_argument("--lr", type=float, default=d.lr, help=f"Adam's learning rate, cosine-annealed (default {d.lr:g})")
    p.add_argument("--val-every", type=int, default=d.val_every,
                   help=f"validate (and keep the best checkpoint) every N steps (default {d.val_every})")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--temporal", action="store_true",
                   help="train the temporal KPCN (a window of 2M+1 warped frames) instead of the shipped "
                        "single-frame network with the OIDN candidate")
    p.add_argument("--error-levels", type=_levels, default=d.error_levels, metavar="L1,L2,…",
                   help="input levels the error network trains on (default: every uniform/adaptive level); "
                        "the loop's own: spp16,loop32,loop64,loop128 (renderloop dataset --loop-branch)")
    p.add_argument("--recipe", default=d.recipe, help=f"the recipe's short name, recorded in the checkpoint "
                                                      f"(default {d.recipe})")
    p.add_argument("--resume", action="store_true", help="continue from OUT/.train_<stage>.pt")
    p.add_argument("--device", default=d.device, help="cpu | cuda (default: cuda when available)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(handler=run_train)


def _levels(text: str) -> tuple[str, ...]:
    return tuple(level.strip() for level in text.split(",") if level.strip())


def train_config(args) -> TrainConfig:
    return TrainConfig(
        data=tuple(args.data), stage=args.stage, out=args.out, steps=args.steps, batch=args.batch, crop=args.crop,
        lr=args.lr, val_every=args.val_every, seed=args.seed, temporal=args.temporal, init=args.init,
        resume=args.resume, device=args.device, quiet=args.quiet, error_levels=args.error_levels, recipe=args.recipe,
    )


def run_train(args) -> int:
    config = train_config(args)
    try:
        config.validate()
    except TrainConfigError as exc:
        print(f"renderloop train: error: {exc}", file=sys.stderr)
        return 2
    from service.loop.tensors import configure_torch_threads
    from service.training.trainer import run_training  # torch and the data loader: only when training

    # RENDERLOOP_TORCH_THREADS holds for training too: two spinning torch threads on a busy
    # 2-core host measured 1.7 CPU-s per step where one thread needs 0.2
    configure_torch_threads()
    try:
        run_training(config, report=print)
    except TrainConfigError as exc:
        print(f"renderloop train: error: {exc}", file=sys.stderr)
        return 2
    return 0
