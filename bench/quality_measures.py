"""The quality report's measures beyond the common metrics: residual noise and kept detail
along λ, temporal flicker, rank correlation of the error map, shadow contrast."""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from bench.common import display, sanitize as clean
from models.losses import smape

REC709_LUMA = (0.2126, 0.7152, 0.0722)  # ITU-R BT.709 luminance weights
FLAT_QUANTILE = 0.5    # pixels whose reference gradient is in the lower half count as "flat"
DETAIL_QUANTILE = 0.75  # the top quarter of reference gradients counts as "detail"


def log_luminance(t: Tensor) -> Tensor:
    """(1,3,H,W) → (1,1,H,W) log(1 + Rec.709 luminance): a scale-tolerant axis for detail measures."""
    w = torch.tensor(REC709_LUMA, dtype=torch.float32).view(1, 3, 1, 1)
    return torch.log1p((clean(t) * w).sum(1, keepdim=True))


def high_pass(x: Tensor) -> Tensor:
    """x − 3×3 box blur (replicate borders): the pixel-scale band where noise and fine detail live."""
    return x - F.avg_pool2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3, stride=1)


def gradient_magnitude(x: Tensor) -> Tensor:
    """Central-difference gradient magnitude (replicate borders)."""
    p = F.pad(x, (1, 1, 1, 1), mode="replicate")
    dx = (p[..., 1:-1, 2:] - p[..., 1:-1, :-2]) / 2
    dy = (p[..., 2:, 1:-1] - p[..., :-2, 1:-1]) / 2
    return torch.sqrt(dx * dx + dy * dy)


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.ravel().astype(np.float64), b.ravel().astype(np.float64)
    a, b = a - a.mean(), b - b.mean()
    denom = math.sqrt(float((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / denom) if denom > 0 else float("nan")


def average_ranks(x: np.ndarray) -> np.ndarray:
    """1-based ranks of x's entries (flattened); tied values share the mean of their ranks."""
    _, inverse, counts = np.unique(x.ravel(), return_inverse=True, return_counts=True)
    last = np.cumsum(counts)                      # the rank of each distinct value's last copy
    return ((last - counts + 1 + last) / 2.0)[inverse.ravel()]


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's ρ: Pearson's r of the average ranks (Spearman 1904; ties as in
    scipy.stats.spearmanr). nan where either input holds a nan or is constant: no ranking."""
    if np.isnan(a).any() or np.isnan(b).any():
        return float("nan")
    return pearson(average_ranks(a), average_ranks(b))


def block_means(x: np.ndarray, block: int) -> np.ndarray:
    """(H, W, …) → the means of its block×block tiles, per channel if it has any (the ragged right
    and bottom edges dropped)."""
    h, w = (x.shape[0] // block) * block, (x.shape[1] // block) * block
    return x[:h, :w].reshape(h // block, block, w // block, block, *x.shape[2:]).mean(axis=(1, 3))


def lambda_measures(d: Tensor, r: Tensor) -> dict[str, float]:
    """Residual noise and kept detail of a result d against the reference r (see the report text)."""
    ld, lr = log_luminance(d), log_luminance(r)
    grad_r = gradient_magnitude(lr)
    flat = grad_r <= torch.quantile(grad_r, FLAT_QUANTILE)
    detail = grad_r >= torch.quantile(grad_r, DETAIL_QUANTILE)
    hd, hr = high_pass(ld), high_pass(lr)
    noise = float((hd - hr).abs()[flat].mean())
    ref_energy = float(hr.abs()[detail].mean())
    ratio = float(hd.abs()[detail].mean()) / ref_energy if ref_energy > 0 else float("nan")
    return {"smape": float(smape(clean(d), clean(r))), "noise": noise, "detail": ratio,
            "grad_corr": pearson(gradient_magnitude(ld).numpy(), grad_r.numpy())}


def flicker(frames: Sequence[Tensor]) -> tuple[float, float]:
    """Mean |consecutive difference|: in linear radiance, and in sRGB 0–255 units."""
    linear = [float((clean(b) - clean(a)).abs().mean()) for a, b in zip(frames, frames[1:])]
    shown = [float((display(clean(b)) - display(clean(a))).abs().mean()) * 255 for a, b in zip(frames, frames[1:])]
    return float(np.mean(linear)), float(np.mean(shown))


def mean_abs_change(frames: Sequence[np.ndarray]) -> float:
    """Mean over consecutive pairs of the mean |difference| (linear radiance): the development
    suite's temporal flicker, taken of residuals (denoised − reference) or, against one fixed
    reference, of the images themselves."""
    return float(np.mean([np.abs(b - a).mean() for a, b in zip(frames, frames[1:])]))


def nanstats(values: Iterable[float]) -> tuple[float, float, float, int]:
    """(mean, min, max, n) over the finite values."""
    v = np.array([x for x in values if np.isfinite(x)], dtype=np.float64)
    if not v.size:
        return float("nan"), float("nan"), float("nan"), 0
    return float(v.mean()), float(v.min()), float(v.max()), int(v.size)


def shadow_contrast_ratio(image: np.ndarray, reference: np.ndarray,
                          region: tuple[float, float, float, float]) -> float:
    """How much of the reference's shadow contrast `image` keeps inside `region` (top, bottom,
    left, right as fractions of the frame; a surface of one albedo crossed by hard shadows).

    The reference splits the region into shadow and lit pixels at the midpoint of its 5th and
    95th luminance percentiles; contrast is (lit − shadow) / (lit + shadow) of the class means.
    Noise leaves the means unbiased (a noisy render scores ≈ 1); blurring or erasing the shadows
    mixes the classes and lowers it. The quality report's goal is ≥ 0.9 of the reference at λ = 1."""
    h, w = reference.shape[:2]
    top, bottom, left, right = region
    window = (slice(int(top * h), int(bottom * h)), slice(int(left * w), int(right * w)))
    luma = np.asarray(REC709_LUMA)
    ref = reference[window] @ luma
    img = np.nan_to_num(image[window]) @ luma
    shadow = ref < 0.5 * (np.percentile(ref, 5) + np.percentile(ref, 95))

    def contrast(values: np.ndarray) -> float:
        lit, dark = float(values[~shadow].mean()), float(values[shadow].mean())
        return (lit - dark) / max(lit + dark, 1e-12)

    return contrast(img) / contrast(ref)
