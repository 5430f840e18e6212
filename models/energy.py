"""Energy conservation of the denoised image.

The noisy mean is an unbiased estimate of the image, so its total is an unbiased estimate of the
image's total energy; a denoiser trained on robust losses (SMAPE, log-space inputs) is not: it
treats rare bright samples as outliers and returns a darker image where light arrives by rare
paths (a spot light seen through fog lost 3.8 % of its energy at 16 spp, docs/suite-quality.md).
One factor per image restores the samples' total, shrunk towards 1 by how well the samples know
it: the weight k = 1 / (1 + (rse/τ)²) is the usual inverse-variance blend of an unbiased estimate
with relative standard error rse against a prior whose error is about τ (the denoiser's own bias,
a few per cent). Fireflies raise rse, so a frame whose total rests on a few samples keeps the
denoiser's energy.
"""
from __future__ import annotations

import torch
from torch import Tensor

GAIN_RANGE = (0.8, 1.25)   # a broken variance estimate never rescales an image by more than this


def sample_energy(color: Tensor, variance: Tensor) -> tuple[Tensor, Tensor]:
    """(N,3,H,W) noisy mean and variance of the mean → per image: mean radiance (N,) and its
    relative standard error (N,). Pixels are independent; a pixel's three channels are taken as
    fully correlated (one path carries all three), which bounds the channel sum's variance by
    3·Σ_c var_c."""
    total = color.sum((1, 2, 3))
    spread = torch.sqrt(3.0 * variance.sum((1, 2, 3)))
    return total / color[0].numel(), spread / total.clamp_min(1e-12)


def conserve_energy(image: Tensor, mean: Tensor, rse: Tensor, tolerance: float) -> Tensor:
    """image (N,3,H,W) rescaled per image towards the samples' mean radiance `mean` (N,),
    trusting it with weight 1 / (1 + (rse/tolerance)²)."""
    current = image.mean((1, 2, 3))
    trust = 1.0 / (1.0 + (rse / tolerance) ** 2)
    gain = 1.0 + trust * (mean / current.clamp_min(1e-12) - 1.0)
    gain = torch.where(current > 1e-12, gain.clamp(*GAIN_RANGE), torch.ones_like(gain))
    return image * gain.view(-1, 1, 1, 1)
