"""Energy conservation of the denoised image.

The noisy mean is an unbiased estimate of the image, so its total is an unbiased estimate of the
image's total energy; a denoiser trained on robust losses (SMAPE, log-space inputs) is not: it
treats rare bright samples as outliers and returns a darker image where light arrives by rare
paths (a spot light seen through fog lost 3.8 % of its energy at 16 spp, docs/suite-quality.md).
One factor per image restores the samples' total, shrunk towards 1 by how well the samples know
it: the weight k = 1 / (1 + (rse/τ)²) is the usual inverse-variance blend of an unbiased estimate
with relative standard error rse against a prior whose error is about τ (the denoiser's own bias,
a few per cent). Fireflies raise rse, so a frame whose total rests on a few samples keeps the
denoiser's energy. Then, with a block size, the same blend block by block
(`conserve_block_energy`): the total is restored where the denoiser lost it, not spread evenly.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
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


@dataclass(frozen=True)
class BlockEnergy:
    """The samples' radiance summed over square blocks of the image: per block (N,1,h,w) its total
    and that total's relative standard error (models.energy's bound, block by block)."""
    block: int
    total: Tensor
    rse: Tensor


def _block_sums(x: Tensor, block: int) -> Tensor:
    """(N,C,H,W) → (N,1,⌈H/b⌉,⌈W/b⌉): each block's sum over channels and pixels (a cut block sums what it has)."""
    h, w = x.shape[-2:]
    summed = F.pad(x.sum(1, keepdim=True), (0, (-w) % block, 0, (-h) % block))
    return F.avg_pool2d(summed, block) * float(block * block)


def block_energy(color: Tensor, variance: Tensor, block: int) -> BlockEnergy:
    total = _block_sums(color, block)
    return BlockEnergy(block, total, torch.sqrt(3.0 * _block_sums(variance, block)) / total.clamp_min(1e-12))


def conserve_block_energy(image: Tensor, samples: BlockEnergy, tolerance: float) -> Tensor:
    """`conserve_energy` block by block: each block's gain towards the samples' block total, with the
    same inverse-variance trust 1 / (1 + (rse/τ)²), interpolated bilinearly between block centres
    so no seam appears. A denoiser does not lose energy evenly: it drops the rare bright paths of
    a caustic or a lamp's glow where they land, and one image-wide factor then brightens every
    other region too. Blocks whose total the samples barely know (a firefly, a dark corner) keep
    the image's own energy; black blocks stay black."""
    h, w = image.shape[-2:]
    current = _block_sums(image, samples.block)
    trust = 1.0 / (1.0 + (samples.rse / tolerance) ** 2)
    gain = (1.0 + trust * (samples.total / current.clamp_min(1e-12) - 1.0)).clamp(*GAIN_RANGE)
    gain = torch.where((current > 1e-12) & (samples.total > 1e-12), gain, torch.ones_like(gain))
    up = F.interpolate(gain, scale_factor=samples.block, mode="bilinear", align_corners=False)
    return image * up[..., :h, :w]


@dataclass(frozen=True)
class SampleEnergy:
    """What the samples say about the image's energy: its mean radiance and that mean's rse (N,),
    and, when asked for, the same block by block."""
    mean: Tensor
    rse: Tensor
    blocks: BlockEnergy | None = None


def measure_energy(color: Tensor, variance: Tensor, block: int = 0) -> SampleEnergy:
    """The samples' energy of (N,3,H,W) noisy mean and variance; block > 0 adds the block totals."""
    return SampleEnergy(*sample_energy(color, variance), block_energy(color, variance, block) if block > 0 else None)


def restore_energy(image: Tensor, samples: SampleEnergy, tolerance: float) -> Tensor:
    """The image-wide factor first, then (with blocks) the block gains on what it left.
    τ = 0 is "off" (DenoiserConfig.energy_tolerance) on a cache prepared with the factor on, too:
    the trust 1 / (1 + (rse/τ)²) is then 0/0 wherever the samples agree exactly (rse 0: a block
    of constant sky), which would write NaN over that block."""
    if tolerance <= 0:
        return image
    image = conserve_energy(image, samples.mean, samples.rse, tolerance)
    return image if samples.blocks is None else conserve_block_energy(image, samples.blocks, tolerance)
