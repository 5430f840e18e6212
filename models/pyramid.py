"""The image pyramid's verbs (Vogels et al. 2018 eq. 5): D, the 2×2 average down; U, the bilinear
2× up; N, the nearest 2× up; and the padding that makes sizes divide by the pyramid's depth."""
from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor

from models.frames import FrameTensors


def down(x: Tensor) -> Tensor:
    """D: 2×2 average pooling (eq. 5) as four strided views: F.avg_pool2d's means at a third of
    its CPU time (0.28 vs 0.96 ms for 3×512², 2 threads); the pyramid pools every buffer."""
    h, w = x.shape[-2] // 2 * 2, x.shape[-1] // 2 * 2
    total = x[..., 0:h:2, 0:w:2] + x[..., 1:h:2, 0:w:2]    # one allocation, then in place
    return total.add_(x[..., 0:h:2, 1:w:2]).add_(x[..., 1:h:2, 1:w:2]).mul_(0.25)


def up(x: Tensor) -> Tensor:
    """U: bilinear 2× upsampling (eq. 5); smoother than nearest, no block seams. Each channel as
    its own image: torch's CPU kernel ran 3-channel NCHW planes ~2.5× slower than three 1-channel
    ones (19 vs 7 ms at 540×962, one thread), same values up to float rounding."""
    n, c, h, w = x.shape
    return F.interpolate(x.reshape(n * c, 1, h, w), scale_factor=2, mode="bilinear", align_corners=False).view(n, c, 2 * h, 2 * w)


def up_nearest(x: Tensor) -> Tensor:
    """N: each coarse pixel onto its own 2×2 block (the compositor's cap, not its blend)."""
    return F.interpolate(x, scale_factor=2, mode="nearest")


def pad_to(x: Tensor, multiple: int) -> Tensor:
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    return F.pad(x, (0, pw, 0, ph), mode="replicate") if (ph or pw) else x


def down_frame(frame: FrameTensors) -> FrameTensors:
    """One pyramid step: average buffers; variance of a 4-pixel mean is the mean variance ÷ 4,
    motion in pixels halves with the resolution."""
    scale = {"variance": 0.25, "motion": 0.5}
    return frame.map(lambda name, t: down(t).mul_(scale[name]) if name in scale else down(t))
