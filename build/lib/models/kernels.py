"""Kernel prediction (Vogels et al. 2018 eqs. 3–4): per-pixel k×k kernels, softmax-normalised.

The softmax makes every output pixel a convex combination of its input neighbourhood, which
bounds the output and keeps training stable. For a temporal window the logits of all frames
share ONE softmax (eq. 4 over frames), so the network decides how much each frame
contributes. Kernels are applied by a loop over the k² offsets: an unfold would materialise a
k²-times copy of the image (≈1.3 GB at 256² for 21×21, DESIGN.md).
"""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor


def pad_for_kernel(image: Tensor, k: int) -> Tensor:
    """Replicate border of k//2 so every tap reads a real pixel (any size, even 1×1)."""
    r = k // 2
    return F.pad(image, (r, r, r, r), mode="replicate")


LOGIT_CLAMP = 40.0   # exp(±40) and a sum of hundreds of taps stay well inside float32


def unnormalised_weights(logits: Tensor) -> Tensor:
    """exp(clamp(logits)) IN PLACE on a fresh (N, F·k², H, W) tensor: softmax without its
    two extra passes. The usual max-shift is replaced by a clamp to ±40 (identical softmax
    unless a logit saturates, where the gradient is ~0 anyway), and the division is
    deferred to one division of the 3-channel output in filter_padded."""
    return logits.clamp_(-LOGIT_CLAMP, LOGIT_CLAMP).exp_()


TILE_PIXELS = 32768   # inference row tiles: a 3-channel output tile (≈ 400 KB) stays in L2 for all taps


def filter_padded(padded: Sequence[Tensor], weights: Tensor, k: int, tile_pixels: int = TILE_PIXELS) -> Tensor:
    """Σ_frames Σ_taps w·x / Σ w: eq. 3 with the joint normalisation of eq. 4.
    padded[f] is frame f's image after pad_for_kernel; weights (N, F·k², H, W) ≥ 0.

    Without autograd the loop runs over row tiles so the accumulator stays in cache across
    the F·k² taps (measured 62 vs 80 ms at 512², 3 frames, one thread). With autograd one
    tile: in-place updates of slices would make backward copy the whole output per tap."""
    h, w = weights.shape[-2:]
    out = torch.zeros(padded[0].shape[:2] + (h, w), dtype=weights.dtype, device=weights.device)
    rows = h if torch.is_grad_enabled() else max(1, tile_pixels // w)
    for y0 in range(0, h, rows):
        y1 = min(h, y0 + rows)
        acc = out if rows >= h else out[:, :, y0:y1]     # no view under autograd
        for f, image in enumerate(padded):
            for dy in range(k):
                for dx in range(k):
                    tap = (f * k + dy) * k + dx
                    acc.addcmul_(weights[:, tap:tap + 1, y0:y1], image[:, :, y0 + dy:y1 + dy, dx:dx + w])
    return out / weights.sum(dim=1, keepdim=True)
