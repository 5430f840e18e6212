"""Training losses (Vogels et al. 2018 §3, §6)."""
from __future__ import annotations

import torch
from torch import Tensor

SMAPE_EPS = 1e-2   # eq. 2: keeps the relative error finite on black pixels


def smape_elementwise(d: Tensor, r: Tensor, eps: float = SMAPE_EPS) -> Tensor:
    """|d − r| / (|d| + |r| + ε) per element (eq. 2 before the mean)."""
    return (d - r).abs() / (d.abs() + r.abs() + eps)


def smape(d: Tensor, r: Tensor, eps: float = SMAPE_EPS) -> Tensor:
    """Eq. 2: symmetric mean absolute percentage error, mean over pixels and channels."""
    return smape_elementwise(d, r, eps).mean()


def smape_map(d: Tensor, r: Tensor, eps: float = SMAPE_EPS) -> Tensor:
    """Per-pixel SMAPE (N,1,H,W), mean over channels: the error predictor's target."""
    return smape_elementwise(d, r, eps).mean(dim=1, keepdim=True)


def l1(d: Tensor, r: Tensor) -> Tensor:
    return (d - r).abs().mean()


def asymmetric_weight(d: Tensor, r: Tensor, c: Tensor, lam: float | Tensor) -> Tensor:
    """1 + (λ − 1)·H((d − r)(r − c)) (eq. 6): λ-fold penalty where the result d overshoots the
    reference r on the side AWAY from the noisy input c — an error the input did not have
    (blur, lost detail, artefacts). Errors between c and r are residual noise and keep weight
    1, so larger λ buys detail at the price of noise. H(0) = 0: exact agreement is never up-weighted."""
    same_side = ((d - r) * (r - c) > 0).to(d.dtype)
    return 1 + (torch.as_tensor(lam, dtype=d.dtype, device=d.device) - 1) * same_side


def asymmetric_loss(d: Tensor, r: Tensor, c: Tensor, lam: float | Tensor, eps: float = SMAPE_EPS) -> Tensor:
    """Eq. 6 with SMAPE as ℓ: mean of ℓ(d, r)·(1 + (λ−1)·H((d−r)(r−c))).
    d denoised, r reference, c noisy input; λ a float or broadcastable (e.g. (N,1,H,W))."""
    return (smape_elementwise(d, r, eps) * asymmetric_weight(d, r, c, lam)).mean()
