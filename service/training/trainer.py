"""Training the denoiser (the paper's staged recipe, or end to end) and the error network.

Random crops, Adam with a cosine schedule, validation every K steps on held-back training
scenes (the held-out split stays unseen for the quality report) with the best checkpoint kept,
resumable, seeded. CPU by default, CUDA automatically when present. `renderloop train` only
maps its arguments onto `TrainConfig`.
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import sys
import time
from pathlib import Path
from typing import Callable

import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from models.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from models.denoiser import POST_TRAINING_SETTINGS, Denoiser, DenoiserConfig
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.losses import smape_map
from models.training import (cut_window, denoiser_lambda_loss, denoiser_loss, denoiser_smape, error_predictor_loss,
                             sample_lambda)
from service.dataset.build import INPUT_ITEMS, DatasetError
from service.dataset.loader import DenoiserDataset, collate_samples
from service.training.config import (DENOISER_STAGES, ERROR_NETWORK_STAGES, FINE_TUNE_STAGES, STAGE_PLANS,
                                     StagePlan, TrainConfig, TrainConfigError)

VALIDATION_EVERY_NTH_SCENE = 8  # scenes with index % 8 == 7 are held back for validation


def _split_items(dataset):
    """Hold back every 8th scene of the train split for validation."""
    scenes = sorted({item.scene for item in dataset.items})
    held = {s for i, s in enumerate(scenes) if i % VALIDATION_EVERY_NTH_SCENE == VALIDATION_EVERY_NTH_SCENE - 1}
    if not held and len(scenes) > 1:
        held = {scenes[-1]}
    return [i for i in dataset.items if i.scene not in held], [i for i in dataset.items if i.scene in held]


def _datasets(config, radius: int, candidate: bool = False, levels: tuple[str, ...] = INPUT_ITEMS):
    """Training and validation items. With config.val_data, validation is that data set's
    held-back scenes, and training leaves those scene seeds out (Noise2Noise data holds the same
    scenes as the clean set it is validated on)."""
    train = DenoiserDataset(config.data_roots, split="train", levels=levels, radius=radius, crop=config.crop,
                            seed=config.seed, candidate=candidate)
    if config.val_data is None:
        train_items, val_items = _split_items(train)
        val = copy.copy(train)
    else:
        val = DenoiserDataset(config.val_data, split="train", levels=levels, radius=radius, crop=None,
                              seed=config.seed, candidate=candidate)
        _, val_items = _split_items(val)
        held = {item.scene for item in val_items}
        train_items = [item for item in train.items if item.scene not in held]
        if not train_items:
            raise DatasetError(f"every training scene is one of {config.val_data}'s validation scenes")
    val.crop = None
    train.items, val.items = train_items, val_items or train_items[:4]
    return train, val


def _provenance(command: str, stage: str, init: Path | None) -> dict:
    """What a checkpoint records about how it was made. A network started from `init` also
    records that file by content (a path such as models/weights/… is overwritten when the result
    ships) and that file's own command."""
    extra = {"command": command, "stage": stage}
    if init is not None:
        digest = hashlib.sha1(Path(init).read_bytes()).hexdigest()[:10]
        earlier = read_checkpoint(init).get("extra", {})
        # the whole chain: a file made from --init records that file's own start as well
        chain = f"; init={earlier['init']}" if isinstance(earlier.get("init"), str) else ""
        extra["init"] = f"{init} sha1 {digest} (command={earlier.get('command', 'unknown')}{chain})"
    return extra


def _batches(dataset, batch: int, seed: int):
    """Endless shuffled batches; a new epoch draws new crops."""
    epoch = 0
    while True:
        dataset.set_epoch(epoch)
        generator = torch.Generator().manual_seed(seed * 1000 + epoch)
        yield from DataLoader(dataset, batch_size=batch, shuffle=True, drop_last=len(dataset) >= batch,
                              collate_fn=collate_samples, generator=generator)
        epoch += 1


def _fit(stage: str, model, loss_fn, val_fn, config: TrainConfig, device, extra: dict, keep_from: int = 0,
         out_name: str | None = None) -> dict:
    """Generic loop: Adam, periodic validation, best checkpoint from step `keep_from` on,
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
            if val < best and step + 1 > keep_from:
                best = val
                save_checkpoint(out_file, model, {**extra, "step": step + 1, "val": val})
            torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                        "step": step + 1, "best": best, "history": history}, state_file)
    return {"best_val": best, "history": history, "checkpoint": str(out_file)}


def _denoiser_to_train(config, device, switches: dict):
    """A fresh network, or --init's weights in a network with the stage's switches (modules the
    earlier stage lacked — compositor, temporal extractor — start fresh)."""
    wanted = {"oidn_candidate": config.oidn_candidate, "temporal": config.temporal}
    if config.init is None:
        sizes = {"width": config.width, "spatial_blocks": config.spatial_blocks, "trunk": config.trunk}
        base = DenoiserConfig(**{k: v for k, v in sizes.items() if v is not None}, **wanted,
                              gate_firefly=config.gate_firefly, candidate_features=config.candidate_features)
        return Denoiser(dataclasses.replace(base, **switches)).to(device)
    trained = load_checkpoint(config.init, expected_kind="denoiser", device=device)
    # a candidate gate the earlier weights lack starts fresh (near "copy the candidate"), and so
    # does a gate layer whose inputs --gate-firefly widens; the checkpoint's post-training
    # settings (gate offsets, energy factor) are not trained through
    wanted["gate_firefly"] = config.gate_firefly or trained.config.gate_firefly
    wanted["candidate_features"] = config.candidate_features or trained.config.candidate_features
    full = dataclasses.replace(trained.config.without_post_training_settings(), multiscale=True, **wanted)
    model = Denoiser(dataclasses.replace(full, **switches)).to(device)
    # Only the gate's widened layer and the trunk's first conv (widened by --candidate-features)
    # may differ in shape; any other mismatch stays a loud error.
    shapes = {name: tensor.shape for name, tensor in model.state_dict().items()}
    weights = {}
    for name, tensor in trained.state_dict().items():
        shape = shapes.get(name, tensor.shape)
        if shape == tensor.shape:
            weights[name] = tensor
        elif name in TRUNK_INPUT_WEIGHTS and shape[0] == tensor.shape[0] and shape[2:] == tensor.shape[2:]:
            weights[name] = widen_input_channels(tensor, shape[1])
        elif not name.startswith("gate."):
            raise ValueError(f"{config.init}: {name} has shape {tuple(tensor.shape)}, this network {tuple(shape)}")
    model.load_state_dict(weights, strict=False)
    return model


# The first convolution of each trunk: the layer --candidate-features widens.
TRUNK_INPUT_WEIGHTS = ("encoder.conv1.weight", "unet.down.0.conv1.weight")


def widen_input_channels(weight: torch.Tensor, channels: int) -> torch.Tensor:
    """A conv weight (out, in, k, k) with zero weights for the input channels appended after
    `in`: the widened network computes exactly what the trained one did until it learns to read them."""
    extra = weight.new_zeros(weight.shape[0], channels - weight.shape[1], *weight.shape[2:])
    return torch.cat([weight, extra], 1)


def train_denoiser(config, device, stage: str = "denoiser", plan: StagePlan = StagePlan({}, "mixed")) -> dict:
    """plan.schedule: "symmetric" (λ = 1), "random" (log λ ~ U(0, log 10)) or "mixed" (λ = 1 for
    --symmetric-fraction of the steps, then random)."""
    torch.manual_seed(config.seed)
    model = _denoiser_to_train(config, device, plan.switches)
    schedule = "symmetric" if config.noisy_targets else plan.schedule
    if plan.trainable is not None and config.init is not None:
        for name, parameter in model.named_parameters():
            parameter.requires_grad_(name.startswith(plan.trainable))
    radius = model.config.temporal_radius if model.config.temporal else 0
    train, val = _datasets(config, radius, model.config.oidn_candidate)
    batches = _batches(train, config.batch, config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    symmetric_steps = {"symmetric": config.steps, "random": 0}.get(schedule, int(config.symmetric_fraction * config.steps))

    def loss_fn(step: int):
        b = next(batches)
        single = bool(torch.rand(1, generator=gen) < 0.5)
        frames, centre = cut_window([f.to(device) for f in b.frames], b.centre, single)
        ref = b.references[b.centre].to(device)
        candidate = None if b.candidates is None else b.candidates.to(device)
        n, _, h, w = ref.shape
        # Vogels et al. train the λ specialisation on top of a network that already denoises:
        # a random λ from step 0 rewards doing nothing (λ > 1 punishes every blur), so the
        # symmetric loss (λ = 1) comes first.
        lam = torch.ones(n, 1, h, w) if step < symmetric_steps else sample_lambda(n, h, w, gen)
        return denoiser_loss(model, frames, centre, ref, lam.to(device), candidate, config.noisy_targets)

    def val_fn() -> float:
        scores = []
        for i in range(len(val)):
            s = val[i]
            frames = [s.noisy.map(lambda _, t, k=k: t[k:k + 1].to(device)) for k in range(s.noisy.color.shape[0])]
            reference = s.reference[s.centre:s.centre + 1].to(device)
            candidate = None if s.candidate is None else s.candidate[None].to(device)
            if schedule == "random":
                scores.append(denoiser_lambda_loss(model, frames, s.centre, reference, candidate=candidate))
            else:
                scores.append(denoiser_smape(model, frames, s.centre, reference, candidate))
        return sum(scores) / len(scores)

    # Checkpoints from a symmetric phase have an untrained λ module (λ would do nothing): when
    # a λ phase follows, the kept one must come from it.
    keep_from = symmetric_steps if symmetric_steps < config.steps else 0
    out_name = "denoiser.pt" if stage in ("denoiser", "lambda", *FINE_TUNE_STAGES) else f"stage_{stage}.pt"
    result = _fit(stage, model, loss_fn, val_fn, config, device, _provenance(config.command_line, stage, config.init),
                  keep_from, out_name)
    if config.keep_settings:
        carry_post_training_settings(config.init, Path(result["checkpoint"]))
    return result


def carry_post_training_settings(source: Path, target: Path) -> None:
    """Rewrite `target` (a denoiser checkpoint) with `source`'s post-training settings; its
    weights and provenance stay as trained."""
    stored = read_checkpoint(source)["config"]
    settings = {name: stored.get(name, getattr(DenoiserConfig, name)) for name in POST_TRAINING_SETTINGS}
    trained = load_checkpoint(target, expected_kind="denoiser")
    model = Denoiser(dataclasses.replace(trained.config, **settings))
    model.load_state_dict(trained.state_dict())
    save_checkpoint(target, model, {**trained.checkpoint_extra, "settings_from": str(source)})


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


def _error_network_to_train(init: Path | None, device, disagreement: bool = False,
                            width: int | None = None, residual: bool = False) -> ErrorPredictor:
    """A fresh error network, or `init`'s weights with its calibration back to none (output scale
    1, no change scale): both are fitted after training, on validation scenes (`renderloop bench
    --calibration --fit-scale`), so a fine-tuning run must neither train through nor keep them. `disagreement` adds the
    kernels/candidate disagreement channel; an `init` without it gets a zero-weighted one, so
    training starts from exactly that network; `residual` adds the residual test the same way
    (after it). `width`: a fresh network's (None: the default)."""
    if init is None:
        # The sample count tells the network how converged each pixel is under the loop's
        # non-uniform counts (every data set's EXRs carry their spp layer).
        sizes = {} if width is None else {"width": width}
        return ErrorPredictor(ErrorPredictorConfig(sample_count_input=True, disagreement_input=disagreement,
                                                   residual_input=residual, **sizes)).to(device)
    trained = load_checkpoint(init, expected_kind="error_predictor", device=device)
    model = ErrorPredictor(dataclasses.replace(
        trained.config, output_scale=1.0, change_scale=None, disagreement_input=disagreement or trained.config.disagreement_input,
        residual_input=residual or trained.config.residual_input)).to(device)
    weights = trained.state_dict()
    weights["head.weight"] = _head_for_inputs(weights["head.weight"], trained.config, model.config)
    model.load_state_dict(weights)
    return model


def _head_for_inputs(weight: torch.Tensor, old: ErrorPredictorConfig, new: ErrorPredictorConfig) -> torch.Tensor:
    """The first conv's weight for `new`'s inputs: `old`'s columns where it had the channel, zero
    columns for the optional channels it gains (each sits at its own place in the input order)."""
    optional = ("disagreement_input", "residual_input")   # ErrorPredictor.forward's order, after the base
    base = weight.shape[1] - sum(int(getattr(old, name)) for name in optional)
    columns, at = [weight[:, :base]], base
    for name in optional:
        if getattr(old, name):
            columns.append(weight[:, at:at + 1])
            at += 1
        elif getattr(new, name):
            columns.append(weight.new_zeros(weight.shape[0], 1, *weight.shape[2:]))
    return torch.cat(columns, 1)


def train_error_predictor(config, device) -> dict:
    torch.manual_seed(config.seed)
    denoiser = load_checkpoint(config.out / "denoiser.pt", expected_kind="denoiser", device=device).eval()
    for p in denoiser.parameters():
        p.requires_grad_(False)
    # --init names an error network only with --stage error (staged and all runs: the denoiser's)
    init = config.init if config.stage == "error" else None
    if config.error_disagreement and not denoiser.config.oidn_candidate:
        raise TrainConfigError(f"--error-disagreement reads the kernels' image against the OIDN candidate's: "
                               f"{config.out / 'denoiser.pt'} has no candidate")
    model = _error_network_to_train(init, device, config.error_disagreement, config.error_width,
                                    config.error_residual)
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

    extra = _provenance(config.command_line, "error", init)
    # The error network predicts one denoiser's error: name that denoiser by content.
    target = config.out / "denoiser.pt"
    extra["denoiser"] = f"{target} sha1 {hashlib.sha1(target.read_bytes()).hexdigest()[:10]}"
    return _fit("error", model, loss_fn, val_fn, config, device, extra)


def run_training(config: TrainConfig, report: Callable[[str], None] = lambda line: None) -> list[str]:
    """Train what `config.stage` names; returns one summary line per trained network, each also
    handed to `report` as soon as that network is done (a staged run takes hours)."""
    config.validate()
    device = torch.device(config.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    config.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    lines = []

    def report_line(line: str) -> str:
        report(line)
        return line

    if config.stage in ("denoiser", "all"):
        result = train_denoiser(config, device)
        lines.append(report_line(f"denoiser: best validation SMAPE {result['best_val']:.4f} → {result['checkpoint']}"))
    stages = list(DENOISER_STAGES) if config.stage == "staged" else [config.stage] if config.stage in STAGE_PLANS else []
    for stage in stages:
        plan = STAGE_PLANS[stage]
        result = train_denoiser(config, device, stage, plan)
        metric = "eq. 6 loss at λ = 2, 4, 10" if plan.schedule == "random" else "SMAPE"
        lines.append(report_line(f"stage {stage}: best validation {metric} {result['best_val']:.4f} → {result['checkpoint']}"))
        config = dataclasses.replace(config, init=Path(result["checkpoint"]), resume=False)  # the next stage starts here
    if config.stage in ERROR_NETWORK_STAGES:
        result = train_error_predictor(config, device)
        lines.append(report_line(f"error predictor: best validation L1 {result['best_val']:.4f} → {result['checkpoint']}"))
    lines.append(report_line(f"trained in {time.perf_counter() - started:.0f} s on {device}"))
    return lines
