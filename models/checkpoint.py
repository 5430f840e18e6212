"""Checkpoints: config (as a dict) + model kind + format version + state dict, so a model is
rebuilt from the file alone and every mismatch fails loudly with CheckpointError. Its `extra`
dict says how it was made: at least the recipe's short name (scripts/train-weights.sh,
docs/models.md) and the hash of the data sets' manifests it trained on (RECIPE_KEY, DATA_KEY)."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable

import torch
import torch.nn as nn

from models.denoiser import Denoiser, DenoiserConfig
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig

FORMAT_VERSION = 2
READABLE_VERSIONS = (FORMAT_VERSION,)
RECIPE_KEY = "recipe"   # extra[...]: the recipe's short name, e.g. "shipped-denoiser"
DATA_KEY = "data"       # extra[...]: "sha256:<hex>" of the data sets' manifests (service.training.provenance)
MODEL_KINDS: dict[str, tuple[type[nn.Module], type]] = {
    Denoiser.kind: (Denoiser, DenoiserConfig),
    ErrorPredictor.kind: (ErrorPredictor, ErrorPredictorConfig),
}

# Config fields that checkpoints written before an option was removed still store (the shipped
# ones among them), each with the value the code now always builds, as a function of the rest of
# the config: a file that stores that value loads as before; any other value was trained for a
# path that is gone, and fails (docs/decisions.md, "Model options removed").
RETIRED_FIELDS: dict[str, dict[str, Callable[[Any], Any]]] = {
    Denoiser.kind: {"source": lambda config: "mitsuba-path",
                    "candidate_features": lambda config: config.candidate_features},
    ErrorPredictor.kind: {"source": lambda config: "mitsuba-path", "sample_count_input": lambda config: True},
}


class CheckpointError(Exception):
    """A checkpoint is missing, unreadable, of another kind/version, or does not fit its model."""


def save_checkpoint(path: str | Path, model: nn.Module, extra: dict[str, Any] | None = None) -> Path:
    """extra: how the weights were made (RECIPE_KEY, DATA_KEY, the step, the validation figure)."""
    kind = getattr(model, "kind", None)
    if kind not in MODEL_KINDS:
        raise CheckpointError(f"cannot save {type(model).__name__}: not one of {sorted(MODEL_KINDS)}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({
        "format_version": FORMAT_VERSION,
        "kind": kind,
        "config": dataclasses.asdict(model.config),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "extra": extra or {},
    }, path)
    return path


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The raw checkpoint dict, after checking the file exists and has our format."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # corrupt, truncated, or not a torch file
        raise CheckpointError(f"cannot read checkpoint {path}: {e}") from e
    if not isinstance(ckpt, dict) or "format_version" not in ckpt:
        raise CheckpointError(f"{path} is not a renderloop checkpoint (no format_version)")
    if ckpt["format_version"] not in READABLE_VERSIONS:
        raise CheckpointError(f"{path} has checkpoint format {ckpt['format_version']}, "
                              f"this code reads formats {', '.join(map(str, READABLE_VERSIONS))}")
    return ckpt


def stored_config(ckpt: dict[str, Any], path: str | Path = "checkpoint") -> Any:
    """The config a checkpoint dict (read_checkpoint) stores, as its config class: each retired
    field checked against the value the code now builds, then left out."""
    kind = ckpt.get("kind")
    if kind not in MODEL_KINDS:
        raise CheckpointError(f"{path} holds unknown model kind {kind!r}; known: {sorted(MODEL_KINDS)}")
    _, config_cls = MODEL_KINDS[kind]
    retired = RETIRED_FIELDS.get(kind, {})
    current = {name: value for name, value in ckpt["config"].items() if name not in retired}
    unknown = set(current) - {f.name for f in dataclasses.fields(config_cls)}
    if unknown:
        raise CheckpointError(f"{path}: config fields {sorted(unknown)} unknown to {config_cls.__name__}")
    try:
        config = config_cls(**current)
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: cannot build {kind} from its config: {e}") from e
    for name, built in retired.items():
        if name in ckpt["config"] and ckpt["config"][name] != built(config):
            raise CheckpointError(f"{path}: {kind} trained with {name}={ckpt['config'][name]!r}, an option this "
                                  f"code no longer has (it builds {name}={built(config)!r}; docs/decisions.md)")
    return config


def load_checkpoint(path: str | Path, expected_kind: str | None = None, device: str | torch.device = "cpu") -> nn.Module:
    """Rebuild the model from its stored config and load the weights (eval mode).
    The stored `extra` dict is attached as model.checkpoint_extra."""
    ckpt = read_checkpoint(path)
    kind = ckpt.get("kind")
    if kind not in MODEL_KINDS:
        raise CheckpointError(f"{path} holds unknown model kind {kind!r}; known: {sorted(MODEL_KINDS)}")
    if expected_kind is not None and kind != expected_kind:
        raise CheckpointError(f"{path} holds a {kind!r} model, expected {expected_kind!r}")
    model_cls, _ = MODEL_KINDS[kind]
    config = stored_config(ckpt, path)
    try:
        model = model_cls(config)
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: cannot build {kind} from its config: {e}") from e
    try:
        model.load_state_dict(ckpt["state_dict"])
    except RuntimeError as e:
        raise CheckpointError(f"{path}: weights do not fit the {kind} built from its config:\n{e}") from e
    model.checkpoint_extra = ckpt.get("extra", {})
    return model.to(device).eval()
