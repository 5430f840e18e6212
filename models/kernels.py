"""Kernel prediction (Vogels et al. 2018 eqs. 3–4): per-pixel k×k kernels, softmax-normalised.

The softmax makes every output pixel a convex combination of its input neighbourhood, which
bounds the output and keeps training stable. For a temporal window the logits of all frames
share ONE softmax (eq. 4 over frames), so the network decides how much each frame
contributes. Kernels are applied by a loop over the k² offsets: an unfold would materialise a
k²-times copy of the image (≈1.3 GB at 256² for 21×21, docs/design.md).
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


def filter_padded(padded: Sequence[Tensor], weights: Tensor, k: int) -> Tensor:
    """Σ_frames Σ_taps w·x / Σ w: eq. 3 with the joint normalisation of eq. 4.
    padded[f] is frame f's image after pad_for_kernel (rows y…y+h+k−1 for output rows y…y+h);
    weights (N, F·k², H, W) ≥ 0. At inference the denoiser calls this per band of rows, so the
    accumulator and the weight planes stay in cache across the F·k² taps (Denoiser._kernel_result)."""
    h, w = weights.shape[-2:]
    out = torch.zeros(padded[0].shape[:2] + (h, w), dtype=weights.dtype, device=weights.device)
    for f, image in enumerate(padded):
        for dy in range(k):
            for dx in range(k):
                tap = (f * k + dy) * k + dx
                out.addcmul_(weights[:, tap:tap + 1], image[:, :, dy:dy + h, dx:dx + w])
    return out / weights.sum(dim=1, keepdim=True)
