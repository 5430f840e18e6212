"""`renderloop train --data DIR --stage ... -o models/weights/`: arguments → TrainConfig → the
trainer. Defaults are TrainConfig's own."""
from __future__ import annotations

import shlex
import sys
from pathlib import Path

from service.training.config import STAGES, TRUNK_NAMES, TrainConfig, TrainConfigError

DEFAULTS = TrainConfig(data=Path("."))


def add_parser(sub) -> None:
    d = DEFAULTS
    p = sub.add_parser("train", help="train the denoiser and/or the error predictor on a built data set")
    p.add_argument("--data", type=Path, required=True, action="append",
                   help="data set folder (renderloop dataset -o ...); repeat it to train on several together")
    p.add_argument("--stage", choices=STAGES, default=d.stage,
                   help="single|multiscale|temporal|lambda: one paper stage (from --init or the previous "
                        "stage's file); staged: all four then the error network; denoiser: end to end; "
                        "gate: only the OIDN candidate's gate of --init (--oidn-candidate); mixing: that gate and the "
                        "scale compositor together; "
                        f"error: the error network; all: denoiser then error (default {d.stage})")
    p.add_argument("-o", "--out", type=Path, default=d.out)
    p.add_argument("--steps", type=int, default=d.steps, help=f"optimiser steps per stage (default {d.steps})")
    p.add_argument("--batch", type=int, default=d.batch)
    p.add_argument("--crop", type=int, default=d.crop)
    p.add_argument("--lr", type=float, default=d.lr)
    p.add_argument("--val-every", type=int, default=d.val_every)
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--width", type=int, default=d.width, help="denoiser feature width (default: model default)")
    p.add_argument("--spatial-blocks", type=int, default=d.spatial_blocks,
                   help="residual blocks of the denoiser's spatial extractor (default: model default)")
    p.add_argument("--trunk", choices=TRUNK_NAMES, default=d.trunk,
                   help="denoiser feature extractor: levels (the paper's, per pyramid level) or unet (one U-Net "
                        "feeding every level, models/unet.py); default: the model's (levels)")
    p.add_argument("--symmetric-fraction", type=float, default=d.symmetric_fraction,
                   help=f"first fraction of denoiser steps trained at λ = 1 before λ is randomised "
                        f"(default {d.symmetric_fraction:g})")
    p.add_argument("--oidn-candidate", action="store_true",
                   help="OIDN's image on the same inputs joins the joint softmax (models/candidate.py)")
    p.add_argument("--gate-firefly", action="store_true",
                   help="with --oidn-candidate: the gate also reads each pixel's relative variance, ≈ 1 where one "
                        "sample dominates (the gate's input layer starts fresh when --init's gate lacks them)")
    p.add_argument("--candidate-features", action="store_true",
                   help="with --oidn-candidate --single-frame: the denoiser's trunk also reads OIDN's image, so its "
                        "kernels are predicted with a clean estimate in view (--init's first conv is widened with "
                        "zero weights: training starts from exactly that network)")
    p.add_argument("--single-frame", action="store_true",
                   help="no temporal extractor: a one-frame network (data sets of single frames)")
    p.add_argument("--init", type=Path, default=d.init,
                   help="start the denoiser from this checkpoint's weights (--stage error: an error network's, "
                        "its calibration scale reset to 1)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/.train_<stage>.pt")
    p.add_argument("--device", default=d.device, help="cpu | cuda (default: cuda when available)")
    p.add_argument("--error-levels", type=_levels, default=d.error_levels, metavar="L1,L2,…",
                   help="input levels the error network trains on (default: every uniform/adaptive level); "
                        "the loop's own: spp16,loop32,loop64,loop128 (renderloop dataset --loop-branch)")
    p.add_argument("--noisy-targets", action="store_true",
                   help="the data's references are independent noisy renders (e.g. renderloop dataset "
                        "--reference-spp 64): train the denoiser at λ = 1 with a loss whose expectation the "
                        "targets' noise leaves unchanged (Noise2Noise); needs --val-data")
    p.add_argument("--val-data", type=Path, default=d.val_data,
                   help="validate on this data set's held-back scenes (clean references), left out of training")
    p.add_argument("--keep-settings", action="store_true",
                   help="write --init's post-training settings (gate offsets, caps, kernel clamp, energy tolerance, "
                        "chosen on validation scenes) into the fine-tuned denoiser; it trains without them")
    p.add_argument("--error-disagreement", action="store_true",
                   help="the error network also reads where the denoiser's kernels' image and its OIDN candidate "
                        "disagree (an --init network without that input gets it with zero weights)")
    p.add_argument("--error-residual", action="store_true",
                   help="the error network also reads what the denoiser removed in units of the samples' noise "
                        "(≈ 1 where it removed only noise; an --init network without it gets it with zero weights)")
    p.add_argument("--error-width", type=int, default=d.error_width,
                   help="feature width of a fresh error network (default: the model's, 16); not with an --init network")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(handler=run_train)


def _levels(text: str) -> tuple[str, ...]:
    return tuple(level.strip() for level in text.split(",") if level.strip())


def train_config(args) -> TrainConfig:
    return TrainConfig(
        data=tuple(args.data), out=args.out, stage=args.stage, steps=args.steps, batch=args.batch, crop=args.crop,
        lr=args.lr, val_every=args.val_every, seed=args.seed, width=args.width, spatial_blocks=args.spatial_blocks,
        trunk=args.trunk, symmetric_fraction=args.symmetric_fraction, oidn_candidate=args.oidn_candidate,
        gate_firefly=args.gate_firefly, candidate_features=args.candidate_features,
        temporal=not args.single_frame, init=args.init, resume=args.resume, device=args.device,
        quiet=args.quiet, error_levels=args.error_levels, noisy_targets=args.noisy_targets, val_data=args.val_data,
        keep_settings=args.keep_settings, error_disagreement=args.error_disagreement,
        error_width=args.error_width, error_residual=args.error_residual,
        command_line="renderloop " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
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
    run_training(config, report=print)
    return 0
