"""Image-quality metrics for reports (not training losses)."""
from __future__ import annotations


import torch
import torch.nn.functional as F
from torch import Tensor

RELMSE_EPS = 1e-2      # relative MSE guard on black reference pixels (as in Vogels et al. tables)
SSIM_C1, SSIM_C2 = 0.01 ** 2, 0.03 ** 2   # Wang et al. 2004 constants for a peak value of 1
SSIM_WINDOW, SSIM_SIGMA = 11, 1.5          # Wang et al. 2004 gaussian window


def relmse(d: Tensor, r: Tensor, eps: float = RELMSE_EPS) -> Tensor:
    """mean((d − r)² / (r² + ε))."""
    return ((d - r) ** 2 / (r * r + eps)).mean()


def psnr(d: Tensor, r: Tensor, peak: float = 1.0) -> Tensor:
    """10·log10(peak² / MSE). For HDR pass tone-mapped (e.g. clamped sRGB) images."""
    mse = ((d - r) ** 2).mean().clamp_min(1e-20)
    return 10 * torch.log10(peak * peak / mse)


def _gaussian_window(size: int, sigma: float, channels: int, like: Tensor) -> Tensor:
    x = torch.arange(size, dtype=like.dtype, device=like.device) - size // 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(channels, 1, size, size).contiguous()


def ssim(d: Tensor, r: Tensor) -> Tensor:
    """Mean SSIM (Wang et al. 2004) with an 11×11 σ=1.5 gaussian window, per channel, images
    in [0, 1]. Borders replicate, so any size works (a 1×1 image compares its single pixel)."""
    c = d.shape[1]
    win = _gaussian_window(SSIM_WINDOW, SSIM_SIGMA, c, d)
    pad = SSIM_WINDOW // 2

    def blur(x: Tensor) -> Tensor:
        return F.conv2d(F.pad(x, (pad,) * 4, mode="replicate"), win, groups=c)

    mu_d, mu_r = blur(d), blur(r)
    var_d = blur(d * d) - mu_d ** 2
    var_r = blur(r * r) - mu_r ** 2
    cov = blur(d * r) - mu_d * mu_r
    num = (2 * mu_d * mu_r + SSIM_C1) * (2 * cov + SSIM_C2)
    den = (mu_d ** 2 + mu_r ** 2 + SSIM_C1) * (var_d + var_r + SSIM_C2)
    return (num / den).mean()


