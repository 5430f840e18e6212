"""The scale compositor of Vogels et al. 2018 (eq. 5): merges a pyramid level's filtered result
with the merged result of the level below it. Part of the λ tail (models.denoiser.Denoiser.merge_levels)."""
from __future__ import annotations

import torch
import torch.nn as nn
from torch import Tensor

from models.features import log_transform
from models.layers import cat_channels_last, conv3x3
from models.pyramid import down, up, up_nearest


class ScaleCompositor(nn.Module):
    """Eq. 5: o = i_f − α·U(D(i_f)) + α·U(i_c) = i_f + α·U(i_c − D(i_f)): swap the fine
    result's low band for the coarse result's where α says so. α comes from a small CNN on
    both results, evaluated at the coarse resolution and upsampled: which band to trust
    is a low-frequency decision, and this keeps the λ tail 4× cheaper.

    The swap is floored at min(i_f, U(i_c)) per pixel. Next to a firefly the fine level keeps
    energy the coarse level removed, so i_c − D(i_f) is strongly negative over the firefly's
    2×2 block and, upsampled, it is subtracted from every neighbour alike: a dark ring (down to
    0.43× of the firefly-free result for a 2000× firefly on hard_shadows, then clipped at 0).
    A pixel pushed below both its own fine estimate and the coarse estimate is one losing energy
    it never had; with the floor the firefly pixel still gives up its excess. The floor also
    keeps radiance ≥ 0 (both levels are), which the next level's log transform needs.

    The swap is capped at max(i_f, N(i_c)), N the nearest upsampling: the mirror case. Along the
    edge of a small very bright emitter next to a dark surface, i_c − D(i_f) is strongly
    positive over the emitter's blocks and the bilinear U spreads it onto the dark neighbours
    (0.09 → 0.75 beside a 800× lamp on night_street at 256 spp, 80 % of the image's relMSE). A
    pixel pushed above both its own fine estimate and its own coarse block's is one receiving
    energy that belongs to another block; N, not U, because U(i_c) there already carries the
    emitter.

    Inside the emitter's own 2×2 block N(i_c) carries the emitter too, so a dark pixel sharing
    that block still takes its light (0.42 → 3.07 on night_street at 256 spp with the U-Net
    trunk, whose coarse levels are OIDN's). Given a full-resolution estimate of each pixel — the
    candidate at this level (DenoiserConfig.candidate_cap) — the swap is also capped at
    max(i_f, candidate): light neither the fine result nor the candidate put on the pixel."""

    def __init__(self, width: int):
        super().__init__()
        self.alpha = nn.Sequential(conv3x3(6, width), nn.ReLU(), conv3x3(width, 1))

    def blend_weight(self, fine_low: Tensor, coarse: Tensor) -> Tensor:
        """α ∈ (0, 1) at the coarse resolution (N,1,h,w)."""
        # channels-last with the ReLU inside the convolution (models.layers.Conv3x3): at 2 MP the
        # NCHW Sequential was a quarter of the finest merge step
        x = cat_channels_last([log_transform(fine_low), log_transform(coarse)])
        first, _, second = self.alpha
        return torch.sigmoid(second(first.relu(x)))

    def forward(self, fine: Tensor, coarse: Tensor, alphas: list[Tensor] | None = None,
                candidate: Tensor | None = None) -> Tensor:
        """candidate: the candidate at the fine level's resolution, for the per-pixel cap."""
        fine_low = down(fine)
        a = self.blend_weight(fine_low, coarse)
        if alphas is not None:
            alphas.append(a)
        if not torch.is_grad_enabled():
            return self._swap_in_place(fine, coarse, fine_low, a, candidate)
        swapped = torch.addcmul(fine, up(a), up(coarse - fine_low))
        # One clamp for the floor and both caps: min(max(f, N), max(f, c)) = max(f, min(N, c)),
        # and floor ≤ fine ≤ cap, so clamping in either order gives the same pixel.
        near = up_nearest(coarse)
        ceiling = torch.maximum(fine, near if candidate is None else torch.minimum(near, candidate))
        return torch.clamp(swapped, min=torch.minimum(fine, up(coarse)), max=ceiling)

    @staticmethod
    def _swap_in_place(fine: Tensor, coarse: Tensor, fine_low: Tensor, a: Tensor, candidate: Tensor | None) -> Tensor:
        """forward's swap and clamp at inference, each full-size result written over the last:
        3⅓ fresh full-resolution planes instead of 8⅓. At 2 MP every fresh 25 MB tensor is page
        faults (an elementwise minimum took 10 ms, measured with torch.profiler)."""
        swapped = up(coarse - fine_low)
        torch.addcmul(fine, up(a), swapped, out=swapped)   # elementwise: writing over an input is safe
        ceiling = up_nearest(coarse)
        if candidate is not None:
            torch.minimum(ceiling, candidate, out=ceiling)
        torch.maximum(ceiling, fine, out=ceiling)
        floor = up(coarse)
        torch.minimum(floor, fine, out=floor)
        return swapped.clamp_(min=floor, max=ceiling)
