"""A U-Net trunk: one feature extractor for every pyramid level (issue 13, item 3).

The paper's trunk (Vogels et al. 2018, Fig. 3) runs its own encoder and residual blocks on each
pyramid level's pooled inputs, so a level's kernels see 13 of its own pixels across: 13 px at
the finest level. Low-frequency noise (blotches several times that size) and a firefly's
neighbourhood are judged from too little. Here one U-Net reads the finest level's inputs once;
its decoder stage at resolution 2^-l gives level l's features, so every level's kernels are
predicted from context reaching the bottleneck one octave below the coarsest level (the
multi-resolution kernel predictor of the Neural Bilateral Grid supplement, Meng et al. 2020).
The kernels, the joint softmax, the compositor and the λ tail are unchanged: the trunk only
says which features each level's kernel head reads.

Cost: the paper's trunk repeats its full stack on every level (≈ 7.9 full-resolution 3×3
convolutions of width w for three levels); this one has 2 encoder + 2 decoder convolutions at
full resolution and twice the width at each coarser stage, ≈ 9.5 by that count; measured by
`python -m bench.experiments.trunk_speed` (docs/unet-trunk.md).
"""
from __future__ import annotations

import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from models.layers import ConvPair, cat_channels_last


def stage_width(width: int, depth: int) -> int:
    """Channels at depth d (0 = full resolution): twice the finest width below it, since a
    coarser stage costs a quarter per channel² and carries the context."""
    return width if depth == 0 else 2 * width


class UNetTrunk(nn.Module):
    """features (N,cin,H,W), H and W divisible by 2^levels → `levels` feature maps of `width`
    channels at H/2^l × W/2^l (finest first): the pyramid's levels."""

    def __init__(self, cin: int, width: int, levels: int):
        super().__init__()
        self.levels = levels
        depths = range(levels + 1)                       # one stage below the coarsest level
        self.down = nn.ModuleList(
            ConvPair(cin if d == 0 else stage_width(width, d - 1), stage_width(width, d)) for d in depths)
        self.up = nn.ModuleList(
            ConvPair(stage_width(width, d) + stage_width(width, d + 1), stage_width(width, d))
            for d in range(levels))
        # the level's kernel head reads `width` channels whatever the stage's own width
        self.out = nn.ModuleList(nn.Identity() if stage_width(width, d) == width
                                 else nn.Conv2d(stage_width(width, d), width, 1) for d in range(levels))

    def forward(self, x: Tensor) -> list[Tensor]:
        skips = []
        for d, stage in enumerate(self.down):
            x = stage(x if d == 0 else F.avg_pool2d(x, 2))
            skips.append(x)
        y = skips[-1]
        outputs: list[Tensor] = []
        for d in reversed(range(self.levels)):
            up = F.interpolate(y, scale_factor=2, mode="bilinear", align_corners=False)
            y = self.up[d](cat_channels_last([skips[d], up]))
            outputs.append(F.relu(self.out[d](y)))
        return outputs[::-1]
