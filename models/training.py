"""Training steps for the denoiser and the error predictor (pure torch: batches in, losses out).

Recipe (Vogels et al. 2018): the denoiser minimises the asymmetric SMAPE loss (eq. 6) with a
per-pixel λ drawn as log λ ~ U(0, log 10) (§6), so one network serves every λ the user
paints; the error predictor is then fit with L1 to the true per-pixel SMAPE of the frozen,
trained denoiser's output (§7).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from models.denoiser import LAMBDA_MAX, Denoiser
from models.error_predictor import ErrorPredictor
from models.frames import FrameTensors
from models.losses import asymmetric_loss, l1, smape, smape_map

LAMBDA_BLOCK = 8  # per-pixel λ maps are drawn on a coarse grid: painted maps are piecewise smooth


@dataclass
class TrainSettings:
    steps: int = 2000
    lr: float = 1e-3
    batch: int = 8
    crop: int = 48
    val_every: int = 200
    seed: int = 0
    single_frame_fraction: float = 0.5  # windows cut to the centre frame, so F = 1 jobs are trained too


def sample_lambda(n: int, height: int, width: int, generator: torch.Generator) -> Tensor:
    """(N,1,H,W) λ with log λ ~ U(0, log 10): half the batch constant per image, half a blocky map."""
    log_max = math.log(LAMBDA_MAX)
    per_image = torch.rand(n, 1, 1, 1, generator=generator) * log_max
    gh, gw = max(1, -(-height // LAMBDA_BLOCK)), max(1, -(-width // LAMBDA_BLOCK))
    blocks = torch.rand(n, 1, gh, gw, generator=generator) * log_max
    per_pixel = F.interpolate(blocks, scale_factor=LAMBDA_BLOCK, mode="nearest")[..., :height, :width]
    use_map = (torch.arange(n) % 2 == 1).view(n, 1, 1, 1)
    return torch.where(use_map, per_pixel, per_image.expand(n, 1, height, width)).exp()


def cut_window(frames: list[FrameTensors], centre: int, single: bool) -> tuple[list[FrameTensors], int]:
    return ([frames[centre]], 0) if single else (frames, centre)


def denoiser_loss(model: Denoiser, frames: list[FrameTensors], centre: int, reference: Tensor,
                  lam: Tensor) -> Tensor:
    out = model(frames, centre, lam)
    return asymmetric_loss(out, reference, frames[centre].color, lam)


def error_predictor_loss(model: ErrorPredictor, denoiser: Denoiser, frame: FrameTensors,
                         reference: Tensor) -> Tensor:
    with torch.no_grad():
        denoised = denoiser([frame], 0, 1.0)
        target = smape_map(denoised, reference)
    return l1(model(frame, denoised), target)


@torch.no_grad()
def denoiser_smape(model: Denoiser, frames: list[FrameTensors], centre: int, reference: Tensor) -> float:
    """Validation metric: symmetric SMAPE at λ = 1 (the default the loop uses)."""
    return float(smape(model(frames, centre, 1.0), reference))


def grad_norm(model: torch.nn.Module) -> float:
    norms = [p.grad.detach().norm() for p in model.parameters() if p.grad is not None]
    return float(torch.stack(norms).norm()) if norms else 0.0
