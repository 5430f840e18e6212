"""Training the denoiser (the paper's staged recipe) and the error network.

Random crops, Adam with a cosine schedule, validation every K steps on held-back training
scenes (the held-out split stays unseen for the quality report) with the best checkpoint kept,
resumable, seeded. CPU by default, CUDA automatically when present. `renderloop train` only
maps its arguments onto `TrainConfig`.
"""
from __future__ import annotations

import copy
import dataclasses
import sys
import time
from pathlib import Path
from typing import Callable

import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from models.checkpoint import load_checkpoint, save_checkpoint
from models.denoiser import POST_TRAINING_SETTINGS, Denoiser, DenoiserConfig, temporal_config
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.losses import smape_map
from models.training import (cut_window, denoiser_lambda_loss, denoiser_loss, denoiser_smape, error_predictor_loss,
                             sample_lambda)
from service.dataset.build import INPUT_ITEMS, DatasetError
from service.dataset.loader import DenoiserDataset, collate_samples
from service.training.config import STAGE_PLANS, StagePlan, TrainConfig, TrainConfigError
from service.training.provenance import file_digest, provenance

VALIDATION_EVERY_NTH_SCENE = 8  # scenes with index % 8 == 7 are held back for validation


def _split_items(dataset):
    """Hold back every 8th scene of the train split for validation."""
    scenes = sorted({item.scene for item in dataset.items})
    held = {s for i, s in enumerate(scenes) if i % VALIDATION_EVERY_NTH_SCENE == VALIDATION_EVERY_NTH_SCENE - 1}
    if not held and len(scenes) > 1:
        held = {scenes[-1]}
    return [i for i in dataset.items if i.scene not in held], [i for i in dataset.items if i.scene in held]


def _datasets(config, radius: int, candidate: bool = False, levels: tuple[str, ...] = INPUT_ITEMS):
    """Training and validation items (every 8th scene held back)."""
    train = DenoiserDataset(config.data_roots, split="train", levels=levels, radius=radius, crop=config.crop,
                            seed=config.seed, candidate=candidate)
    train_items, val_items = _split_items(train)
    val = copy.copy(train)
    val.crop = None
    train.items, val.items = train_items, val_items or train_items[:4]
    return train, val


def _batches(dataset, batch: int, seed: int):
    """Endless shuffled batches; a new epoch draws new crops."""
    epoch = 0
    while True:
        dataset.set_epoch(epoch)
        generator = torch.Generator().manual_seed(seed * 1000 + epoch)
        yield from DataLoader(dataset, batch_size=batch, shuffle=True, drop_last=len(dataset) >= batch,
                              collate_fn=collate_samples, generator=generator)
        epoch += 1


def _fit(stage: str, model, loss_fn, val_fn, config: TrainConfig, device, extra: dict,
         out_name: str | None = None) -> dict:
    """Generic loop: Adam, periodic validation, the best checkpoint kept,
    resumable state."""
    out_file = config.out / (out_name or "error_predictor.pt")
    state_file = config.out / f".train_{stage}.pt"
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=config.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=config.steps, eta_min=config.lr * 0.05)
    start, best, history = 0, float("inf"), []
    if config.resume and state_file.is_file():
        saved = torch.load(state_file, map_location=device, weights_only=False)
        model.load_state_dict(saved["model"])
        opt.load_state_dict(saved["opt"])
        sched.load_state_dict(saved["sched"])
        start, best, history = saved["step"], saved["best"], saved["history"]
    bar = tqdm(range(start, config.steps), desc=f"train {stage}", disable=config.quiet, file=sys.stderr,
               initial=start, total=config.steps)
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
        if (step + 1) % config.val_every == 0 or step + 1 == config.steps:
            model.eval()
            val = val_fn()
            history.append({"step": step + 1, "train_loss": running, "val": val})
            if val < best:
                best = val
                save_checkpoint(out_file, model, {**extra, "step": step + 1, "val": val})
            torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                        "step": step + 1, "best": best, "history": history}, state_file)
    return {"best_val": best, "history": history, "checkpoint": str(out_file)}


def base_config(config: TrainConfig) -> DenoiserConfig:
    """The network a run trains: the shipped configuration, or the temporal KPCN (--temporal)."""
    return temporal_config() if config.temporal else DenoiserConfig()


def _denoiser_to_train(config: TrainConfig, device, switches: dict) -> Denoiser:
    """A fresh network, or --init's weights in a network with the stage's switches (modules the
    earlier stage lacked — compositor, temporal extractor — start fresh). Either trains without
    the post-training settings."""
    if config.init is None:
        start = base_config(config)
    else:
        trained = load_checkpoint(config.init, expected_kind="denoiser", device=device)
        start = dataclasses.replace(trained.config, multiscale=True, temporal=config.temporal)
    model = Denoiser(dataclasses.replace(start.without_post_training_settings(), **switches)).to(device)
    if config.init is not None:
        shapes = {name: tensor.shape for name, tensor in model.state_dict().items()}
        for name, tensor in trained.state_dict().items():
            if name in shapes and shapes[name] != tensor.shape:
                raise ValueError(f"{config.init}: {name} has shape {tuple(tensor.shape)}, this network {tuple(shapes[name])}")
        model.load_state_dict(trained.state_dict(), strict=False)
    return model


def train_denoiser(config: TrainConfig, device, stage: str, plan: StagePlan) -> dict:
    """plan.schedule: "symmetric" (λ = 1) or "random" (log λ ~ U(0, log 10))."""
    torch.manual_seed(config.seed)
    model = _denoiser_to_train(config, device, plan.switches)
    if plan.trainable is not None and config.init is not None:
        for name, parameter in model.named_parameters():
            parameter.requires_grad_(name.startswith(plan.trainable))
    radius = model.config.temporal_radius if model.config.temporal else 0
    train, val = _datasets(config, radius, model.config.oidn_candidate)
    batches = _batches(train, config.batch, config.seed)
    gen = torch.Generator().manual_seed(config.seed)

    def loss_fn(step: int):
        b = next(batches)
        single = bool(torch.rand(1, generator=gen) < 0.5)
        frames, centre = cut_window([f.to(device) for f in b.frames], b.centre, single)
        ref = b.references[b.centre].to(device)
        candidate = None if b.candidates is None else b.candidates.to(device)
        n, _, h, w = ref.shape
        # Vogels et al. train the λ specialisation on top of a network that already denoises:
        # a random λ from step 0 rewards doing nothing (λ > 1 punishes every blur), so the
        # symmetric stages come first.
        lam = torch.ones(n, 1, h, w) if plan.schedule == "symmetric" else sample_lambda(n, h, w, gen)
        return denoiser_loss(model, frames, centre, ref, lam.to(device), candidate)

    def val_fn() -> float:
        scores = []
        for i in range(len(val)):
            s = val[i]
            frames = [s.noisy.map(lambda _, t, k=k: t[k:k + 1].to(device)) for k in range(s.noisy.color.shape[0])]
            reference = s.reference[s.centre:s.centre + 1].to(device)
            candidate = None if s.candidate is None else s.candidate[None].to(device)
            if plan.schedule == "random":
                scores.append(denoiser_lambda_loss(model, frames, s.centre, reference, candidate=candidate))
            else:
                scores.append(denoiser_smape(model, frames, s.centre, reference, candidate))
        return sum(scores) / len(scores)

    extra = provenance(config.recipe, config.data_roots, stage, config.init)
    result = _fit(stage, model, loss_fn, val_fn, config, device, extra, out_name=plan.out_name)
    if plan.out_name == "denoiser.pt":
        write_post_training_settings(Path(result["checkpoint"]), base_config(config))
    return result


def write_post_training_settings(target: Path, settings_from: DenoiserConfig) -> None:
    """Rewrite `target` (a finished denoiser) with `settings_from`'s post-training settings — the
    defaults, chosen on the validation scenes for the shipped weights (docs/models.md); weights and
    provenance stay as trained."""
    trained = load_checkpoint(target, expected_kind="denoiser")
    settings = {name: getattr(settings_from, name) for name in POST_TRAINING_SETTINGS}
    model = Denoiser(dataclasses.replace(trained.config, **settings))
    model.load_state_dict(trained.state_dict())
    save_checkpoint(target, model, trained.checkpoint_extra)


def start_at_typical_error(model, denoiser, batch, device) -> None:
    """Start the error network at the median true SMAPE of a batch, with a quiet output layer.

    Softplus has a vanishing gradient below zero: from the default init the first steps of L1
    overshoot into that region and the network dies at ~0 for every pixel (predictions of
    1e-17). Starting at the L1 optimum of a constant avoids the overshoot.
    """
    with torch.no_grad():
        frame = batch.frames[0].to(device)
        candidate = None if batch.candidates is None else batch.candidates.to(device)
        target = smape_map(denoiser([frame], 0, 1.0, candidate), batch.references[0].to(device))
        median = float(target.median().clamp_min(1e-4))
        model.out.weight.mul_(0.1)
        model.out.bias.fill_(median + torch.log(-torch.expm1(torch.tensor(-median))).item())


def _error_network_to_train(init: Path | None, device, disagreement: bool) -> ErrorPredictor:
    """A fresh error network of the shipped configuration (reading the kernels/candidate
    disagreement when the denoiser has a candidate), or `init`'s weights; either with its
    calibration back to none (output scale 1, no change scale): both are fitted after training,
    on validation scenes (`renderloop bench --calibration --fit-scale`)."""
    uncalibrated = {"output_scale": 1.0, "change_scale": None}
    if init is None:
        return ErrorPredictor(ErrorPredictorConfig(disagreement_input=disagreement, **uncalibrated)).to(device)
    trained = load_checkpoint(init, expected_kind="error_predictor", device=device)
    if trained.config.disagreement_input != disagreement:
        raise TrainConfigError(f"{init} {'reads' if trained.config.disagreement_input else 'does not read'} the "
                               f"kernels/candidate disagreement; the denoiser it would learn "
                               f"{'has no' if not disagreement else 'has a'} candidate")
    model = ErrorPredictor(dataclasses.replace(trained.config, **uncalibrated)).to(device)
    model.load_state_dict(trained.state_dict())
    return model


def train_error_predictor(config, device) -> dict:
    torch.manual_seed(config.seed)
    denoiser = load_checkpoint(config.out / "denoiser.pt", expected_kind="denoiser", device=device).eval()
    for p in denoiser.parameters():
        p.requires_grad_(False)
    init = config.init
    model = _error_network_to_train(init, device, denoiser.config.oidn_candidate)
    train, val = _datasets(config, 0, denoiser.config.oidn_candidate, config.error_levels or INPUT_ITEMS)
    batches = _batches(train, config.batch, config.seed + 1)
    if init is None:
        start_at_typical_error(model, denoiser, next(_batches(train, config.batch, config.seed + 2)), device)

    def loss_fn(step: int):
        b = next(batches)
        candidate = None if b.candidates is None else b.candidates.to(device)
        return error_predictor_loss(model, denoiser, b.frames[0].to(device), b.references[0].to(device), candidate)

    @torch.no_grad()
    def val_fn() -> float:
        losses = []
        for i in range(len(val)):
            s = val[i]
            frame = s.noisy.map(lambda _, t: t[:1].to(device))
            candidate = None if s.candidate is None else s.candidate[None].to(device)
            losses.append(float(error_predictor_loss(model, denoiser, frame, s.reference[:1].to(device),
                                                     candidate)))
        return sum(losses) / len(losses)

    extra = provenance(config.recipe, config.data_roots, "error", init)
    # The error network predicts one denoiser's error: name that denoiser by content.
    extra["denoiser"] = file_digest(config.out / "denoiser.pt")
    return _fit("error", model, loss_fn, val_fn, config, device, extra)


def run_training(config: TrainConfig, report: Callable[[str], None] = lambda line: None) -> list[str]:
    """Train what `config.stage` names; returns its summary lines, each also handed to `report`."""
    config.validate()
    device = torch.device(config.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    config.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    lines = []

    def report_line(line: str) -> str:
        report(line)
        return line

    if config.stage in STAGE_PLANS:
        plan = STAGE_PLANS[config.stage]
        result = train_denoiser(config, device, config.stage, plan)
        metric = "eq. 6 loss at λ = 2, 4, 10" if plan.schedule == "random" else "SMAPE"
        lines.append(report_line(f"stage {config.stage}: best validation {metric} {result['best_val']:.4f} "
                                 f"→ {result['checkpoint']}"))
    else:
        result = train_error_predictor(config, device)
        lines.append(report_line(f"error predictor: best validation L1 {result['best_val']:.4f} → {result['checkpoint']}"))
    lines.append(report_line(f"trained in {time.perf_counter() - started:.0f} s on {device}"))
    return lines
