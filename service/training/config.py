"""What one `renderloop train` run does, as a typed config (no torch here, so the CLI can
build and check it before the trainer is imported). The network it trains is the shipped
configuration (models.denoiser.DenoiserConfig(), models.error_predictor.ErrorPredictorConfig());
`temporal` selects the temporal KPCN (models.denoiser.temporal_config) instead. The recipe that
rebuilds the shipped weights from scratch is scripts/train-weights.sh (docs/models.md)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple


# Vogels et al. train in stages, each starting from the previous one's weights: a single-frame
# single-scale KPCN, then the scale compositor, then the temporal extractor, then the λ
# specialisation; the error network last, on the frozen denoiser.
class StagePlan(NamedTuple):
    switches: dict  # DenoiserConfig fields the stage's network sets
    schedule: str  # λ during training: "symmetric" (λ = 1) or "random"
    # Parameter-name prefixes that learn when the stage starts from --init (None: all of them).
    trainable: tuple[str, ...] | None = None
    # The file the stage writes in --out: a stage file, or the finished denoiser (which carries
    # the post-training settings, models.denoiser.POST_TRAINING_SETTINGS).
    out_name: str = "denoiser.pt"


STAGE_PLANS: dict[str, StagePlan] = {
    "single": StagePlan({"multiscale": False}, "symmetric", out_name="stage_single.pt"),
    "multiscale": StagePlan({}, "symmetric", out_name="stage_multiscale.pt"),
    # the temporal KPCN's own stage (--temporal): the temporal extractor joins, starting fresh
    "temporal": StagePlan({}, "symmetric", out_name="stage_temporal.pt"),
    # Only the OIDN candidate's gate learns, at λ = 1: end to end, the kernels' own loss dominates
    # and the gate stayed near its initial share (docs/decisions.md).
    "gate": StagePlan({}, "symmetric", ("gate.",), out_name="stage_gate.pt"),
    # Only the λ directions learn (the MLP s(λ) and ΔW); the trunk and the symmetric kernel head
    # W₀ stay as the symmetric stages left them, so λ = 1 is exactly that network (the λ module is
    # anchored at s(1)) and the service's cached features stay valid.
    "lambda": StagePlan({}, "random", ("specialise.mix.", "specialise.delta")),
}
STAGES = (*STAGE_PLANS, "error")
FINE_TUNE_STAGES = ("gate", "lambda")   # they train part of a network: --init names it
CANDIDATE_STAGES = ("gate",)            # the shipped (single-frame, OIDN candidate) network's only
TEMPORAL_STAGES = ("temporal",)         # --temporal's only
DEFAULT_RECIPE = "custom"               # a run outside scripts/train-weights.sh


class TrainConfigError(ValueError):
    """A training setting is out of range; the message names it."""


@dataclass(frozen=True)
class TrainConfig:
    data: Path | tuple[Path, ...]   # one data set folder, or several trained on together
    stage: str = "single"
    out: Path = Path("out/train")
    steps: int = 1500  # optimiser steps
    batch: int = 8
    crop: int = 64
    lr: float = 1e-3
    val_every: int = 250
    seed: int = 0
    temporal: bool = False  # the temporal KPCN (a window of 2M+1 frames) instead of the shipped single-frame network
    init: Path | None = None  # start from this checkpoint: the denoiser's (--stage error: the error network's)
    resume: bool = False  # continue from OUT/.train_<stage>.pt
    device: str | None = None  # cpu | cuda (None: cuda when available)
    quiet: bool = False
    # Input levels the error network trains on (None: every uniform/adaptive level). The loop's
    # own inputs are ("spp16", "loop32", "loop64", "loop128"): `renderloop dataset --loop-branch`.
    error_levels: tuple[str, ...] | None = None
    recipe: str = DEFAULT_RECIPE  # the recipe's short name, recorded in the checkpoint

    @property
    def data_roots(self) -> tuple[Path, ...]:
        return tuple(self.data) if isinstance(self.data, (tuple, list)) else (self.data,)

    def validate(self) -> None:
        if not self.data_roots:
            raise TrainConfigError("--data names no data set")
        if self.stage not in STAGES:
            raise TrainConfigError(f"unknown stage {self.stage!r}; choose one of {', '.join(STAGES)}")
        for name, least in (("steps", 1), ("batch", 1), ("crop", 1), ("val_every", 1)):
            if getattr(self, name) < least:
                raise TrainConfigError(f"--{name.replace('_', '-')} must be >= {least}")
        if self.stage in FINE_TUNE_STAGES and self.init is None:
            raise TrainConfigError(f"--stage {self.stage} trains part of a denoiser: name it with --init")
        if self.stage in CANDIDATE_STAGES and self.temporal:
            raise TrainConfigError(f"--stage {self.stage} trains the OIDN candidate's gate, which the temporal "
                                   "network has not: leave out --temporal")
        if self.stage in TEMPORAL_STAGES and not self.temporal:
            raise TrainConfigError(f"--stage {self.stage} trains the temporal extractor: add --temporal")
        if not self.recipe or any(c.isspace() or c == "/" for c in self.recipe):
            raise TrainConfigError(f"--recipe is a short name without spaces or slashes, got {self.recipe!r}")
