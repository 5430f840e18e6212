"""Start the API server for the tests: `python service_launcher.py PORT`.

It runs exactly what `uvicorn --factory service.api.serve:app_from_env` runs. The one
difference: while the shipped weights (models/weights/*.pt) do not exist yet, it points
$RENDERLOOP_WEIGHTS_DIR at small *untrained* networks saved under $RENDERLOOP_DATA_DIR/weights,
so the denoiser path (features cache, λ re-denoise) is exercised by real networks. Once the
trained weights ship, they are used as they are.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import torch
import uvicorn

import models.pretrained as pretrained
from models.checkpoint import save_checkpoint
from models.denoiser import Denoiser, DenoiserConfig
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from service.api.serve import DATA_DIR_ENV, SHUTDOWN_GRACE_SECONDS, app_from_env


def untrained_weights(directory: Path) -> Path:
    """Seeded, so every start (also after a kill) writes the same networks for this code."""
    torch.manual_seed(0)
    denoiser = Denoiser(DenoiserConfig(width=8, spatial_blocks=1))
    # The λ module starts as "no specialisation" (zero-initialised layers); give those
    # weights so λ changes the image.
    for parameter in denoiser.specialise.parameters():
        if parameter.dim() > 1 and not parameter.detach().any():
            torch.nn.init.normal_(parameter, std=0.5)
    save_checkpoint(directory / pretrained.DENOISER_FILE, denoiser)
    save_checkpoint(directory / pretrained.ERROR_PREDICTOR_FILE, ErrorPredictor(ErrorPredictorConfig(width=8)))
    return directory


def main(port: int) -> None:
    shipped = pretrained.SHIPPED_WEIGHTS_DIR
    if not (shipped / pretrained.DENOISER_FILE).is_file():
        os.environ[pretrained.WEIGHTS_DIR_ENV] = str(untrained_weights(Path(os.environ[DATA_DIR_ENV]) / "weights"))
    uvicorn.run(app_from_env(), host="127.0.0.1", port=port, log_level="warning",
                timeout_graceful_shutdown=SHUTDOWN_GRACE_SECONDS)


if __name__ == "__main__":
    main(int(sys.argv[1]))
