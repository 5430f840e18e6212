"""An external denoiser's image as one more candidate in the KPCN's joint softmax.

Vogels et al. 2018 eq. 4 normalises the kernels of all frames of the window jointly, so every
output pixel is a convex combination of its (warped) input neighbourhoods. A second denoiser's
output on the same inputs (Intel Open Image Denoise, computed by the service) joins that
combination as one more candidate with one logit g per pixel:

    o = Σ_t e^{ℓ_t} x_t / (Σ_t e^{ℓ_t} + e^{ℓ_c}) + e^{ℓ_c} c / (Σ_t e^{ℓ_t} + e^{ℓ_c}).

Writing the candidate's logit relative to the taps' log-partition, ℓ_c = g + log Σ_t e^{ℓ_t},
turns this into o = (1 − σ(g))·kernel_result + σ(g)·c: the same convex combination, computed
without touching the tap loop, with the candidate's weight σ(g) ∈ [0, 1] readable directly and
initialised from a plain bias (start near "copy the candidate", the safe end).

g comes from the centre frame's pre-λ kernel-head features plus a few statistics that say
where the candidate disagrees with the samples more than their noise explains (a candidate that
erased a hard shadow or a thin bright edge does), and goes through its own λ module, so λ
steers the candidate's weight like it steers the kernels (eq. 6).
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from models.features import log_transform
from models.layers import Pointwise

GATE_INIT_LOGIT = 1.0   # σ(1) ≈ 0.73: a fresh gate leans to the candidate (the safe start)
# g = G·tanh(raw/G): the first CPU run let g run off to saturation within 250 steps (σ' ≈ 0, the
# validation SMAPE then equal to OIDN's to 9 digits for the rest of the run, kernels starved);
# the bound keeps σ' ≥ 4.5e-5 and σ within 4.5e-5 of 0 or 1.
GATE_LOGIT_BOUND = 10.0
VARIANCE_FLOOR = 1e-4   # z-score guard where all samples agreed (variance 0: black or constant pixels)
WINDOWS = (3, 7)        # box windows of the disagreement statistic: single pixels are too noisy to judge
N_STATS = len(WINDOWS) + 2


def disagreement(noisy: Tensor, candidate: Tensor, variance: Tensor) -> Tensor:
    """Per-pixel squared difference of noisy mean and candidate in units of the mean's variance
    (mean over colour channels): ≈ 1 where the candidate sits inside the noise, ≫ 1 where it
    left the samples behind (erased structure) or where the samples hold a firefly."""
    d = noisy - candidate
    return (d * d / (variance + VARIANCE_FLOOR)).mean(1, keepdim=True)


def _in_image_count(n: int, r: int, like: Tensor) -> Tensor:
    """How many of positions i−r … i+r lie inside 0 … n−1, for each i."""
    i = torch.arange(n, device=like.device)
    return ((i + r).clamp(max=n - 1) - (i - r).clamp(min=0) + 1).to(like.dtype)


def box_mean(x: Tensor, k: int) -> Tensor:
    """Mean over the k×k window around each pixel, over the pixels inside the image (what
    F.avg_pool2d(x, k, 1, k // 2, count_include_pad=False) returns): a separable sum of shifted
    views of the zero-padded planes divided by the in-image count, which factors into rows ×
    columns. ~4× faster than the pooling at 512² (it is a third of the gate's preparation)."""
    r = k // 2
    h, w = x.shape[-2:]
    padded = F.pad(x, (r, r, r, r))
    rows = padded[..., :, 0:w].clone()
    for dx in range(1, k):
        rows += padded[..., :, dx:dx + w]
    total = rows[..., 0:h, :].clone()
    for dy in range(1, k):
        total += rows[..., dy:dy + h, :]
    return total / (_in_image_count(h, r, x).view(-1, 1) * _in_image_count(w, r, x))


def gate_statistics(noisy: Tensor, candidate: Tensor, variance: Tensor) -> Tensor:
    """(N, N_STATS, H, W): log(1 + box-averaged z) per window, log brightness of the candidate,
    and the mean |log(1+noisy) − log(1+candidate)|, all compressed to a CNN-friendly range."""
    z = disagreement(noisy, candidate, variance)
    pooled = [box_mean(z, k) for k in WINDOWS]
    ln, lc = log_transform(noisy), log_transform(candidate)
    stats = [*(torch.log1p(p) for p in pooled), lc.mean(1, keepdim=True), (ln - lc).abs().mean(1, keepdim=True)]
    return torch.cat(stats, 1)


class CandidateGate(nn.Module):
    """prepare: features → gate hidden planes (λ-independent, cached);
    apply: hidden planes + λ code → candidate logit g (N,1,H,W) through a λ module."""

    def __init__(self, cin: int, width: int, lambda_module: nn.Module):
        super().__init__()
        self.hidden = Pointwise(cin + N_STATS, width)
        self.specialise = lambda_module          # k = 1: one logit per pixel
        with torch.no_grad():
            self.specialise.base[:, -1].fill_(GATE_INIT_LOGIT)   # the bias column (ones input last)

    def prepare(self, kernel_features: Tensor, noisy: Tensor, candidate: Tensor, variance: Tensor) -> Tensor:
        """(N,C,H,W) centre features and images → (N,1,width+1,H,W) with a ones channel last.
        The hidden layer reads [features; statistics] as two GEMMs, W·[f; s] = W_f·f + W_s·s,
        instead of concatenating its input: one full-size copy fewer per pyramid level."""
        stats = gate_statistics(noisy, candidate, variance)
        n, c, height, width = kernel_features.shape
        weight = self.hidden.weight
        h = torch.baddbmm(self.hidden.bias.view(1, -1, 1), weight[:, :c].expand(n, -1, -1),
                          kernel_features.reshape(n, c, -1))
        h = h.baddbmm_(weight[:, c:].expand(n, -1, -1), stats.reshape(n, stats.shape[1], -1)).relu_()
        h = h.view(n, -1, height, width)
        return torch.cat([h, torch.ones_like(h[:, :1])], 1).unsqueeze(1)

    def weight(self, hidden: Tensor, code: Tensor, offset: float = 0.0) -> Tensor:
        """σ(g) ∈ [0, 1]: the candidate's share of the joint softmax, (N,1,H,W).

        offset: a logit added before the bound (DenoiserConfig.gate_offset), chosen after
        training at λ = 1 and tapered to nothing at λ = 10, b·(1 − log λ / log 10): λ = 1 is
        the setting chosen for the lowest error, λ = 10 stays the trained network's own most
        detailed end, so the slider keeps its whole range (a constant offset shrank the
        λ 1 → 10 change of the image 4–5×)."""
        raw = self.specialise(hidden, code) + offset * (1.0 - code)
        return torch.sigmoid(torch.tanh(raw / GATE_LOGIT_BOUND) * GATE_LOGIT_BOUND)


def clamp_around(result: Tensor, candidate: Tensor, t: float, code: Tensor) -> Tensor:
    """result clamped to [c/(1+t'), c·(1+t')] around the candidate c, t' = t / (1 − code)
    (DenoiserConfig.kernel_clamp): the band at λ = 1 (code 0), wider with λ and gone at λ = 10
    (code 1), per pixel under a λ map. The result stays between the kernels' value and c."""
    band = 1.0 + t / (1.0 - code).clamp_min(1e-6)
    return torch.minimum(torch.maximum(result, candidate / band), candidate * band)


def blend(kernel_result: Tensor, candidate: Tensor, weight: Tensor) -> Tensor:
    """(1 − w)·kernel_result + w·candidate: eq. 4 with the candidate as one more term."""
    return torch.lerp(kernel_result, candidate, weight)
