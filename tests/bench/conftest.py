"""Fixtures of the measurement wing's tests: weights folders holding tiny untrained networks
(the reports' plumbing is under test, not the networks' quality)."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from models.checkpoint import save_checkpoint
from models.denoiser import Denoiser, temporal_config
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.pretrained import DENOISER_FILE, ERROR_PREDICTOR_FILE
from tests.models.conftest import PLAIN_ERROR_NETWORK


def tiny_denoiser() -> Denoiser:
    torch.manual_seed(0)
    return Denoiser(temporal_config(width=8, lambda_width=8, temporal_blocks=1)).eval()


def write_tiny_weights(folder: Path) -> Path:
    save_checkpoint(folder / DENOISER_FILE, tiny_denoiser(), extra={"command": "tiny untrained"})
    save_checkpoint(folder / ERROR_PREDICTOR_FILE, ErrorPredictor(ErrorPredictorConfig(width=8, blocks=1, **PLAIN_ERROR_NETWORK)))
    return folder


@pytest.fixture(scope="module")
def tiny_weights_dir(tmp_path_factory) -> Path:
    """A weights folder (denoiser.pt, error_predictor.pt) of tiny untrained networks."""
    return write_tiny_weights(tmp_path_factory.mktemp("weights"))
