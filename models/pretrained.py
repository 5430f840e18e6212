"""Trained weights: the shipped ones in models/weights/ (produced by `renderloop train`) or a
folder the caller names (`--weights DIR`, `RENDERLOOP_WEIGHTS_DIR`).

Networks are loaded once, at start-up, and passed to whoever denoises; nothing here is
reassigned at run time.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from models.checkpoint import CheckpointError, load_checkpoint
from models.denoiser import Denoiser
from models.error_predictor import ErrorMap, ErrorPredictor

SHIPPED_WEIGHTS_DIR = Path(__file__).parent / "weights"
WEIGHTS_DIR_ENV = "RENDERLOOP_WEIGHTS_DIR"
DENOISER_FILE = "denoiser.pt"
ERROR_PREDICTOR_FILE = "error_predictor.pt"


@dataclass(frozen=True)
class Networks:
    """The two networks one render loop needs: the denoiser and its error predictor."""

    denoiser: Denoiser
    error_predictor: ErrorMap   # the network, or a stand-in with its surface (models.error_predictor.ErrorMap)


def weights_dir(explicit: str | Path | None = None) -> Path:
    """The folder to load from: `explicit`, else $RENDERLOOP_WEIGHTS_DIR, else the shipped one."""
    if explicit is not None:
        return Path(explicit)
    from_env = os.environ.get(WEIGHTS_DIR_ENV)
    return Path(from_env) if from_env else SHIPPED_WEIGHTS_DIR


def _load(directory: Path, name: str, kind: str, device: str | torch.device):
    path = directory / name
    if not path.is_file():
        raise CheckpointError(
            f"no trained {kind} at {path}. Produce it with `renderloop train ...` (see "
            f"`renderloop train --help`) and point --weights / {WEIGHTS_DIR_ENV} at its folder")
    return load_checkpoint(path, expected_kind=kind, device=device)


def load_denoiser(directory: str | Path | None = None, device: str | torch.device = "cpu") -> Denoiser:
    return _load(weights_dir(directory), DENOISER_FILE, Denoiser.kind, device)


def load_error_predictor(directory: str | Path | None = None, device: str | torch.device = "cpu") -> ErrorPredictor:
    return _load(weights_dir(directory), ERROR_PREDICTOR_FILE, ErrorPredictor.kind, device)


def load_networks(directory: str | Path | None = None, device: str | torch.device = "cpu") -> Networks:
    """Both networks from one folder (see `weights_dir` for which), in eval mode."""
    networks = Networks(
        denoiser=load_denoiser(directory, device).eval(),
        error_predictor=load_error_predictor(directory, device).eval(),
    )
    if networks.error_predictor.config.disagreement_input and not networks.denoiser.config.oidn_candidate:
        # refused at start-up, not at a job's first iteration
        raise CheckpointError(f"{weights_dir(directory) / ERROR_PREDICTOR_FILE} reads where the denoiser's kernels "
                              f"and its OIDN candidate disagree, but {DENOISER_FILE} beside it has no candidate")
    return networks
