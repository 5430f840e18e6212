"""The shipped weights in models/weights/ (produced by `renderloop train`)."""
from __future__ import annotations

from pathlib import Path

import torch

from models.checkpoint import CheckpointError, load_checkpoint
from models.denoiser import Denoiser
from models.error_predictor import ErrorPredictor

DEFAULT_WEIGHTS_DIR = Path(__file__).parent / "weights"
DENOISER_FILE = "denoiser.pt"
ERROR_PREDICTOR_FILE = "error_predictor.pt"


def _load(name: str, kind: str, device: str | torch.device):
    path = DEFAULT_WEIGHTS_DIR / name
    if not path.is_file():
        raise CheckpointError(
            f"no trained {kind} at {path}. Produce it with `renderloop train ...` (see "
            f"`renderloop train --help`) and copy the resulting {name} into {DEFAULT_WEIGHTS_DIR}/")
    return load_checkpoint(path, expected_kind=kind, device=device)


def load_default_denoiser(device: str | torch.device = "cpu") -> Denoiser:
    return _load(DENOISER_FILE, Denoiser.kind, device)


def load_default_error_predictor(device: str | torch.device = "cpu") -> ErrorPredictor:
    return _load(ERROR_PREDICTOR_FILE, ErrorPredictor.kind, device)
