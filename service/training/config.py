"""What one `renderloop train` run does, as a typed config (no torch here, so the CLI can
build and check it before the trainer is imported)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

# Vogels et al. train in stages, each starting from the previous one's weights: a single-frame
# single-scale KPCN, then the scale compositor, then the temporal extractor, then the λ
# specialisation; the error network last, on the frozen denoiser. `denoiser` trains the full
# network end to end instead (λ = 1 for `symmetric_fraction` of the steps, then random λ).
class StagePlan(NamedTuple):
    switches: dict  # DenoiserConfig fields the stage's network sets
    schedule: str  # λ during training: "symmetric" (λ = 1) or "random"
    # Parameter-name prefixes that learn when the stage starts from --init (None: all of them).
    trainable: tuple[str, ...] | None = None


DENOISER_STAGES: dict[str, StagePlan] = {
    "single": StagePlan({"multiscale": False, "temporal": False}, "symmetric"),
    "multiscale": StagePlan({"temporal": False}, "symmetric"),
    "temporal": StagePlan({}, "symmetric"),
    # Only the λ directions learn (the MLP s(λ) and ΔW); the trunk and the symmetric kernel head
    # W₀ stay as the symmetric stages left them, so λ = 1 is exactly that network (the λ module is
    # anchored at s(1)) and the service's cached features stay valid.
    "lambda": StagePlan({}, "random", ("specialise.mix.", "specialise.delta")),
}
# Fine-tuning of one part of a trained denoiser (--init), everything else frozen; not part of
# `staged`. `gate`: only the OIDN candidate's gate learns (models/candidate.py), at λ = 1 — end
# to end, the kernels' own loss dominates and the gate stayed near its initial share
# (docs/oidn-candidate.md).
# `mixing`: the gate and the scale compositor's α together — kernels trained without the
# candidate never taught α what to do when the coarse levels are OIDN's (docs/unet-trunk.md).
FINE_TUNE_STAGES: dict[str, StagePlan] = {
    "gate": StagePlan({}, "symmetric", ("gate.",)),
    "mixing": StagePlan({}, "symmetric", ("gate.", "composite.")),
}
STAGE_PLANS = {**DENOISER_STAGES, **FINE_TUNE_STAGES}
STAGES = (*STAGE_PLANS, "staged", "denoiser", "error", "all")
ERROR_NETWORK_STAGES = ("error", "staged", "all")  # the stages that train an error network
# models.denoiser.TRUNKS, restated: this module imports no torch (the CLI checks a config before
# loading the trainer); a test keeps the two equal.
TRUNK_NAMES = ("levels", "unet")
# Stages whose loss reads which side of the reference a pixel lies on, or its exact error.
NEEDS_CLEAN_REFERENCES = ("lambda", "staged", "error", "all")


class TrainConfigError(ValueError):
    """A training setting is out of range; the message names it."""


@dataclass(frozen=True)
class TrainConfig:
    data: Path | tuple[Path, ...]   # one data set folder, or several trained on together
    out: Path = Path("models/weights")
    stage: str = "all"
    steps: int = 1500  # optimiser steps per stage
    batch: int = 8
    crop: int = 48
    lr: float = 1e-3
    val_every: int = 150
    seed: int = 0
    width: int | None = None  # denoiser feature width (None: the model's default)
    spatial_blocks: int | None = None  # residual blocks of the spatial extractor (None: default)
    trunk: str | None = None  # denoiser feature extractor: levels | unet (None: the model's default)
    symmetric_fraction: float = 0.5  # end to end: first fraction of steps at λ = 1
    oidn_candidate: bool = False  # OIDN's image as one more candidate of the joint softmax
    gate_firefly: bool = False  # the candidate gate also reads the relative variance (models.candidate)
    candidate_features: bool = False  # the denoiser's trunk also reads OIDN's image (single-frame, models.denoiser)
    temporal: bool = True  # False: a single-frame denoiser (no temporal extractor, one-frame windows)
    init: Path | None = None  # start from this checkpoint: the denoiser's (--stage error: the error network's)
    resume: bool = False  # continue from OUT/.train_<stage>.pt
    device: str | None = None  # cpu | cuda (None: cuda when available)
    quiet: bool = False
    command_line: str = ""  # recorded in every checkpoint
    # Input levels the error network trains on (None: every uniform/adaptive level). The loop's
    # own inputs are ("spp16", "loop32", "loop64", "loop128"): `renderloop dataset --loop-branch`.
    error_levels: tuple[str, ...] | None = None
    # The data's references are independent noisy renders (Noise2Noise targets, e.g. `renderloop
    # dataset --reference-spp 64`): the denoiser trains with models.losses.noisy_target_loss at
    # λ = 1, and validates on `val_data`'s clean references.
    noisy_targets: bool = False
    # Validate on this data set's held-back scenes (every 8th) instead of `data`'s own; those
    # scenes are then left out of training wherever `data` holds them too.
    val_data: Path | None = None
    # Write --init's post-training settings (models.denoiser.POST_TRAINING_SETTINGS: gate offsets,
    # caps, clamp, energy tolerance) into the trained denoiser: a fine-tune trains without them,
    # and they were chosen on validation scenes for the weights it starts from.
    keep_settings: bool = False
    # The error network also reads where the denoiser's kernels' image and its OIDN candidate
    # disagree (models/kernel_disagreement.py); the denoiser in `out` must have the candidate.
    error_disagreement: bool = False
    # The error network also reads the residual test (models.error_predictor.residual_feature).
    error_residual: bool = False
    # A fresh error network's feature width (None: ErrorPredictorConfig's default, 16).
    error_width: int | None = None

    @property
    def data_roots(self) -> tuple[Path, ...]:
        return tuple(self.data) if isinstance(self.data, (tuple, list)) else (self.data,)

    def validate(self) -> None:
        if not self.data_roots:
            raise TrainConfigError("--data names no data set")
        if self.stage not in STAGES:
            raise TrainConfigError(f"unknown stage {self.stage!r}; choose one of {', '.join(STAGES)}")
        for name, least in (("steps", 1), ("batch", 1), ("crop", 1), ("val_every", 1), ("width", 1),
                            ("spatial_blocks", 0), ("error_width", 1)):
            value = getattr(self, name)
            if value is not None and value < least:
                raise TrainConfigError(f"--{name.replace('_', '-')} must be >= {least}")
        if self.trunk is not None and self.trunk not in TRUNK_NAMES:
            raise TrainConfigError(f"--trunk must be one of {', '.join(TRUNK_NAMES)}, got {self.trunk!r}")
        if not 0.0 <= self.symmetric_fraction <= 1.0:
            raise TrainConfigError("--symmetric-fraction must lie in [0, 1]")
        if self.stage in FINE_TUNE_STAGES and self.init is None:
            raise TrainConfigError(f"--stage {self.stage} fine-tunes a trained denoiser: name it with --init")
        if self.noisy_targets and self.val_data is None:
            raise TrainConfigError("--noisy-targets needs --val-data: a data set with clean references to validate "
                                   "on (checkpoints ranked against noisy targets are ranked by their noise)")
        if self.noisy_targets and self.stage in NEEDS_CLEAN_REFERENCES:
            raise TrainConfigError(f"--noisy-targets trains the denoiser at λ = 1; --stage {self.stage} needs clean "
                                   "references (eq. 6's λ weighting and the error network's SMAPE target)")
        if self.keep_settings and (self.init is None or self.stage in ERROR_NETWORK_STAGES):
            raise TrainConfigError("--keep-settings carries --init's settings into a fine-tuned denoiser: name it with "
                                   "--init, and a denoiser stage (not staged, all or error)")
        if self.error_disagreement and self.stage not in ERROR_NETWORK_STAGES:
            raise TrainConfigError("--error-disagreement is an input of the error network: use it with --stage error "
                                   "(or staged, all)")
        if self.error_residual and self.stage not in ERROR_NETWORK_STAGES:
            raise TrainConfigError("--error-residual is an input of the error network: use it with --stage error "
                                   "(or staged, all)")
        if self.error_width is not None and (self.stage not in ERROR_NETWORK_STAGES
                                             or (self.init is not None and self.stage == "error")):
            raise TrainConfigError("--error-width sets the width of a fresh error network: use it with --stage error "
                                   "(or staged, all) and without --init (an --init network keeps its own width)")
        if self.gate_firefly and not self.oidn_candidate:
            raise TrainConfigError("--gate-firefly adds statistics to the OIDN candidate's gate: add --oidn-candidate")
        if self.candidate_features and not (self.oidn_candidate and not self.temporal):
            raise TrainConfigError("--candidate-features feeds the OIDN candidate to a single-frame trunk: "
                                   "add --oidn-candidate and --single-frame")
        if self.stage in ("gate", "mixing") and not self.oidn_candidate:
            raise TrainConfigError(f"--stage {self.stage} trains the OIDN candidate's gate: add --oidn-candidate")
