"""`renderloop train --data DIR --stage denoiser|error|all -o models/weights/`.

Random crops, Adam, validation every K steps on held-back training scenes (the held-out
split stays unseen for the quality report) with the best checkpoint kept, resumable, seeded,
tqdm with the running loss. CPU by default, CUDA automatically when present.
"""
from __future__ import annotations

import shlex
import sys
import time
from pathlib import Path

# Vogels et al. train in stages, each starting from the previous one's weights: a single-frame
# single-scale KPCN, then the scale compositor, then the temporal extractor, then the λ
# specialisation; the error network last, on the frozen denoiser. `denoiser` trains the full
# network end to end instead (λ = 1 for --symmetric-fraction of the steps, then random λ).
DENOISER_STAGES: dict[str, tuple[dict, str]] = {   # stage → (DenoiserConfig switches, λ schedule)
    "single": ({"multiscale": False, "temporal": False}, "symmetric"),
    "multiscale": ({"temporal": False}, "symmetric"),
    "temporal": ({}, "symmetric"),
    "lambda": ({}, "random"),
}
STAGES = (*DENOISER_STAGES, "staged", "denoiser", "error", "all")
VALIDATION_EVERY_NTH_SCENE = 8  # scenes with index % 8 == 7 are held back for validation


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


def _split_items(dataset):
    """Hold back every 8th scene of the train split for validation."""
    scenes = sorted({item.scene for item in dataset.items})
    held = {s for i, s in enumerate(scenes) if i % VALIDATION_EVERY_NTH_SCENE == VALIDATION_EVERY_NTH_SCENE - 1}
    if not held and len(scenes) > 1:
        held = {scenes[-1]}
    return [i for i in dataset.items if i.scene not in held], [i for i in dataset.items if i.scene in held]


def _datasets(args, radius: int):
    import copy

    from service.dataset.loader import DenoiserDataset

    train = DenoiserDataset(args.data, split="train", radius=radius, crop=args.crop, seed=args.seed)
    train_items, val_items = _split_items(train)
    val = copy.copy(train)
    val.crop = None
    train.items, val.items = train_items, val_items or train_items[:4]
    return train, val


def _batches(dataset, batch: int, seed: int):
    """Endless shuffled batches; a new epoch draws new crops."""
    import torch
    from torch.utils.data import DataLoader

    from service.dataset.loader import collate_samples

    epoch = 0
    while True:
        dataset.set_epoch(epoch)
        generator = torch.Generator().manual_seed(seed * 1000 + epoch)
        yield from DataLoader(dataset, batch_size=batch, shuffle=True, drop_last=len(dataset) >= batch,
                              collate_fn=collate_samples, generator=generator)
        epoch += 1


def _fit(stage: str, model, loss_fn, val_fn, args, device, extra: dict, keep_from: int = 0,
         out_name: str | None = None) -> dict:
    """Generic loop: Adam, periodic validation, best checkpoint from step `keep_from` on,
    resumable state."""
    import torch
    from tqdm import tqdm

    from models.checkpoint import save_checkpoint

    out_file = args.out / (out_name or "error_predictor.pt")
    state_file = args.out / f".train_{stage}.pt"
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=args.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=args.steps, eta_min=args.lr * 0.05)
    start, best, history = 0, float("inf"), []
    if args.resume and state_file.is_file():
        saved = torch.load(state_file, map_location=device, weights_only=False)
        model.load_state_dict(saved["model"])
        opt.load_state_dict(saved["opt"])
        sched.load_state_dict(saved["sched"])
        start, best, history = saved["step"], saved["best"], saved["history"]
    bar = tqdm(range(start, args.steps), desc=f"train {stage}", disable=args.quiet, file=sys.stderr,
               initial=start, total=args.steps)
    running = None
    for step in bar:
        model.train()
        loss = loss_fn(step)
        if not torch.isfinite(loss):
            raise RuntimeError(f"{stage}: loss became non-finite at step {step}")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        value = loss.item()
        running = value if running is None else 0.95 * running + 0.05 * value
        bar.set_postfix(loss=f"{running:.4f}", best=f"{best:.4f}", refresh=False)
        if (step + 1) % args.val_every == 0 or step + 1 == args.steps:
            model.eval()
            val = val_fn()
            history.append({"step": step + 1, "train_loss": running, "val": val})
            if val < best and step + 1 > keep_from:
                best = val
                save_checkpoint(out_file, model, {**extra, "step": step + 1, "val": val})
            torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                        "step": step + 1, "best": best, "history": history}, state_file)
    return {"best_val": best, "history": history, "checkpoint": str(out_file)}


def _denoiser_to_train(args, device, switches: dict):
    """A fresh network, or --init's weights in a network with the stage's switches (modules the
    earlier stage lacked — compositor, temporal extractor — start fresh)."""
    import dataclasses

    from models.checkpoint import load_checkpoint
    from models.denoiser import Denoiser, DenoiserConfig

    if args.init is None:
        sizes = {"width": args.width, "spatial_blocks": args.spatial_blocks}
        base = DenoiserConfig(**{k: v for k, v in sizes.items() if v is not None})
        return Denoiser(dataclasses.replace(base, **switches)).to(device)
    trained = load_checkpoint(args.init, expected_kind="denoiser", device=device)
    full = dataclasses.replace(trained.config, temporal=True, multiscale=True)
    model = Denoiser(dataclasses.replace(full, **switches)).to(device)
    model.load_state_dict(trained.state_dict(), strict=False)
    return model


def train_denoiser(args, device, stage: str = "denoiser", switches: dict | None = None,
                   schedule: str = "mixed") -> dict:
    """schedule: "symmetric" (λ = 1), "random" (log λ ~ U(0, log 10)) or "mixed" (λ = 1 for
    --symmetric-fraction of the steps, then random)."""
    import torch

    from models.training import cut_window, denoiser_lambda_loss, denoiser_loss, denoiser_smape, sample_lambda

    torch.manual_seed(args.seed)
    model = _denoiser_to_train(args, device, switches or {})
    if stage == "lambda" and args.init is not None:
        # Only the λ directions learn (the MLP s(λ) and ΔW); the trunk and the symmetric kernel
        # head W₀ stay as the symmetric stages left them, so λ = 1 is exactly that network
        # (the λ module is anchored at s(1)) and the service's cached features stay valid.
        for name, parameter in model.named_parameters():
            parameter.requires_grad_(name.startswith(("specialise.mix.", "specialise.delta")))
    train, val = _datasets(args, model.config.temporal_radius)
    batches = _batches(train, args.batch, args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    symmetric_steps = {"symmetric": args.steps, "random": 0}.get(schedule, int(args.symmetric_fraction * args.steps))

    def loss_fn(step: int):
        b = next(batches)
        single = bool(torch.rand(1, generator=gen) < 0.5)
        frames, centre = cut_window([f.to(device) for f in b.frames], b.centre, single)
        ref = b.references[b.centre].to(device)
        n, _, h, w = ref.shape
        # Vogels et al. train the λ specialisation on top of a network that already denoises:
        # a random λ from step 0 rewards doing nothing (λ > 1 punishes every blur), so the
        # symmetric loss (λ = 1) comes first.
        lam = torch.ones(n, 1, h, w) if step < symmetric_steps else sample_lambda(n, h, w, gen)
        return denoiser_loss(model, frames, centre, ref, lam.to(device))

    def val_fn() -> float:
        scores = []
        for i in range(len(val)):
            s = val[i]
            frames = [s.noisy.map(lambda _, t, k=k: t[k:k + 1].to(device)) for k in range(s.noisy.color.shape[0])]
            reference = s.reference[s.centre:s.centre + 1].to(device)
            if schedule == "random":
                scores.append(denoiser_lambda_loss(model, frames, s.centre, reference))
            else:
                scores.append(denoiser_smape(model, frames, s.centre, reference))
        return sum(scores) / len(scores)

    # Checkpoints from a symmetric phase have an untrained λ module (λ would do nothing): when
    # a λ phase follows, the kept one must come from it.
    keep_from = symmetric_steps if symmetric_steps < args.steps else 0
    out_name = "denoiser.pt" if stage in ("denoiser", "lambda") else f"stage_{stage}.pt"
    return _fit(stage, model, loss_fn, val_fn, args, device, {"command": args.command_line, "stage": stage},
                keep_from, out_name)


def start_at_typical_error(model, denoiser, batch, device) -> None:
    """Start the error network at the median true SMAPE of a batch, with a quiet output layer.

    Softplus has a vanishing gradient below zero: from the default init the first steps of L1
    overshoot into that region and the network dies at ~0 for every pixel (seen in the first
    run: predictions of 1e-17). Starting at the L1 optimum of a constant avoids the overshoot.
    """
    import torch

    from models.losses import smape_map

    with torch.no_grad():
        frame = batch.frames[0].to(device)
        target = smape_map(denoiser([frame], 0, 1.0), batch.references[0].to(device))
        median = float(target.median().clamp_min(1e-4))
        model.out.weight.mul_(0.1)
        model.out.bias.fill_(median + torch.log(-torch.expm1(torch.tensor(-median))).item())


def train_error_predictor(args, device) -> dict:
    import torch

    from models.checkpoint import load_checkpoint
    from models.error_predictor import ErrorPredictor
    from models.training import error_predictor_loss

    torch.manual_seed(args.seed)
    denoiser = load_checkpoint(args.out / "denoiser.pt", expected_kind="denoiser", device=device).eval()
    for p in denoiser.parameters():
        p.requires_grad_(False)
    model = ErrorPredictor().to(device)
    train, val = _datasets(args, 0)
    batches = _batches(train, args.batch, args.seed + 1)
    start_at_typical_error(model, denoiser, next(_batches(train, args.batch, args.seed + 2)), device)

    def loss_fn(step: int):
        b = next(batches)
        return error_predictor_loss(model, denoiser, b.frames[0].to(device), b.references[0].to(device))

    @torch.no_grad()
    def val_fn() -> float:
        losses = []
        for i in range(len(val)):
            s = val[i]
            frame = s.noisy.map(lambda _, t: t[:1].to(device))
            losses.append(float(error_predictor_loss(model, denoiser, frame, s.reference[:1].to(device))))
        return sum(losses) / len(losses)

    return _fit("error", model, loss_fn, val_fn, args, device, {"command": args.command_line, "stage": "error"})


def run_train(args) -> int:
    import torch

    for name, least in (("steps", 1), ("batch", 1), ("crop", 1), ("val_every", 1), ("width", 1), ("spatial_blocks", 0)):
        value = getattr(args, name)
        if value is not None and value < least:
            print(f"renderloop train: error: --{name.replace('_', '-')} must be >= {least}", file=sys.stderr)
            return 2
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    args.command_line = "renderloop " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    if args.stage in ("denoiser", "all"):
        result = train_denoiser(args, device)
        print(f"denoiser: best validation SMAPE {result['best_val']:.4f} → {result['checkpoint']}")
    stages = list(DENOISER_STAGES) if args.stage == "staged" else [args.stage] if args.stage in DENOISER_STAGES else []
    for stage in stages:
        switches, schedule = DENOISER_STAGES[stage]
        result = train_denoiser(args, device, stage, switches, schedule)
        metric = "eq. 6 loss at λ = 2, 4, 10" if schedule == "random" else "SMAPE"
        print(f"stage {stage}: best validation {metric} {result['best_val']:.4f} → {result['checkpoint']}")
        args.init, args.resume = Path(result["checkpoint"]), False  # the next stage starts here
    if args.stage in ("error", "all", "staged"):
        result = train_error_predictor(args, device)
        print(f"error predictor: best validation L1 {result['best_val']:.4f} → {result['checkpoint']}")
    print(f"trained in {time.perf_counter() - started:.0f} s on {device}")
    return 0
