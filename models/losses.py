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


def noisy_target_loss(d: Tensor, t: Tensor, eps: float = SMAPE_EPS) -> Tensor:
    """Relative MSE with the result's own magnitude as the denominator and no gradient through
    it: mean((d − t)² / (sg|d| + ε)²) (Noise2Noise, Lehtinen et al. 2018, §3.4: their loss for
    Monte Carlo renders trained against noisy targets).

    Why it may be trained against an independent noisy render t of the reference r: for target
    noise of mean 0, E[(d − t)²] = (d − r)² + Var t, and Var t does not depend on d, so the
    expected gradient is the one the clean reference gives (the denominator is a constant to the
    gradient). SMAPE (eq. 2) and eq. 6's H((d − r)(r − c)) have no such property: their
    expectation over t is another function of d, minimised elsewhere than at r."""
    scale = (d.detach().abs() + eps) ** 2
    return ((d - t) ** 2 / scale).mean()


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
