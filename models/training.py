"""Training steps for the denoiser and the error predictor (pure torch: batches in, losses out).

Recipe (Vogels et al. 2018): the denoiser minimises the asymmetric SMAPE loss (eq. 6) with a
per-pixel λ drawn as log λ ~ U(0, log 10) (§6), so one network serves every λ the user
paints; the error predictor is then fit with L1 to the true per-pixel SMAPE of the frozen,
trained denoiser's output (§7).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from models.denoiser import LAMBDA_MAX, Denoiser, DenoiserCache
from models.pyramid import down, pad_to
from models.exposure import Exposure
from models.error_predictor import ErrorPredictor
from models.features import demodulate
from models.frames import FrameTensors
from models.kernel_disagreement import apply_for_error_network
from models.losses import asymmetric_loss, l1, smape, smape_map

LAMBDA_BLOCK = 8  # per-pixel λ maps are drawn on a coarse grid: painted maps are piecewise smooth
VALIDATION_LAMBDAS = (2.0, 4.0, 10.0)  # λ-stage validation: spread over log λ ∈ (0, log 10]
COARSE_LEVEL_WEIGHT = 0.5  # weight of the coarse levels' own loss next to the composited result's
KERNEL_PATH_WEIGHT = 0.5   # with a candidate image: weight of eq. 6 on the kernels' result alone


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
                  lam: Tensor, candidate: Tensor | None = None) -> Tensor:
    """Eq. 6 on the composited result, plus COARSE_LEVEL_WEIGHT × eq. 6 on each coarse level's
    own result against the pooled reference.

    Why the per-level term: a coarse result reaches the output only through the compositor's α
    (eq. 5), so its gradient is scaled by α. Without this term α falls to ~0 within the first few
    hundred steps and the coarse kernels stop learning: the coarsest level then scores barely
    better than plain pooling of the noisy input (the "Pyramid levels" table of the quality
    report shows both), and the multi-scale network is single-scale with extra work. Training
    each level on its own target keeps the coarse path useful, so α has something to choose.
    """
    cache = model.prepare(frames, centre, candidate)
    kernel_only: list[Tensor] = []
    levels = model.filter_levels(cache, lam, kernel_only)
    noisy = frames[centre].color
    loss = asymmetric_loss(model.merge_levels(cache, levels), reference, noisy, lam)
    if candidate is not None:
        # Why: the kernels reach the output only through (1 − σ(g)); where the gate trusts the
        # candidate their gradient vanishes, and from random init the gate learned to trust it
        # everywhere (the kernels never got good enough to be chosen). Their own loss keeps
        # them learning, so the gate has a real second candidate to weigh.
        loss = loss + KERNEL_PATH_WEIGHT * asymmetric_loss(model.merge_levels(cache, kernel_only), reference, noisy,
                                                           lam)
        levels = kernel_only
    if len(levels) > 1:
        loss = loss + COARSE_LEVEL_WEIGHT * coarse_levels_loss(model, cache, levels, noisy, reference, lam)
    return loss


def coarse_levels_loss(model: Denoiser, cache: DenoiserCache, levels: list[Tensor], noisy: Tensor, reference: Tensor,
                       lam: Tensor) -> Tensor:
    """Mean of eq. 6 over the coarse levels, in the demodulated space the levels filter, with
    reference, noisy input and λ pooled like the pyramid pools its inputs."""
    align = model.config.alignment
    if cache.exposure is not None:   # the levels filter exposed radiance (models.exposure)
        reference, noisy = cache.exposure.forward(reference), cache.exposure.forward(noisy)
    target = demodulate(pad_to(reference, align), cache.albedo)
    noisy = demodulate(pad_to(torch.nan_to_num(noisy, nan=0.0, posinf=0.0, neginf=0.0), align), cache.albedo)
    lam = pad_to(torch.as_tensor(lam, dtype=target.dtype, device=target.device).expand_as(reference[:, :1]), align)
    terms = []
    for result in levels[1:]:
        target, noisy, lam = down(target), down(noisy), down(lam)
        terms.append(asymmetric_loss(result, target, noisy, lam))
    return torch.stack(terms).mean()


def error_predictor_loss(model: ErrorPredictor, denoiser: Denoiser, frame: FrameTensors,
                         reference: Tensor, candidate: Tensor | None = None) -> Tensor:
    with torch.no_grad():
        denoised, disagreement = denoise_for_error_network(model, denoiser, frame, candidate)
        # the error the network reads its inputs at: SMAPE's ε is absolute (models.exposure)
        exposure = Exposure.of(frame.color)
        target = smape_map(exposure.forward(denoised), exposure.forward(reference))
    return l1(model(frame, denoised, disagreement), target)


def denoise_for_error_network(model: ErrorPredictor, denoiser: Denoiser, frame: FrameTensors,
                              candidate: Tensor | None) -> tuple[Tensor, Tensor | None]:
    """The denoised image at λ = 1, and the kernels/candidate disagreement if `model` reads it."""
    cache = denoiser.prepare([frame], 0, candidate)
    return apply_for_error_network(denoiser, cache, candidate, 1.0, model.config.disagreement_input)


@torch.no_grad()
def denoiser_smape(model: Denoiser, frames: list[FrameTensors], centre: int, reference: Tensor,
                   candidate: Tensor | None = None) -> float:
    """Validation metric: symmetric SMAPE at λ = 1 (the default the loop uses)."""
    return float(smape(model(frames, centre, 1.0, candidate), reference))


@torch.no_grad()
def denoiser_lambda_loss(model: Denoiser, frames: list[FrameTensors], centre: int, reference: Tensor,
                         lambdas: tuple[float, ...] = VALIDATION_LAMBDAS, candidate: Tensor | None = None) -> float:
    """Validation metric of the λ stage: mean eq. 6 over λ > 1. SMAPE at λ = 1 cannot rank λ-stage
    checkpoints: the anchored λ module leaves λ = 1 exactly as the symmetric stages made it."""
    cache = model.prepare(frames, centre, candidate)
    noisy = frames[centre].color
    return sum(float(asymmetric_loss(model.apply(cache, lam), reference, noisy, lam)) for lam in lambdas) / len(lambdas)
