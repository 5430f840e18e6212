"""The final image: the denoised estimate, falling back per region towards the raw image (the
samples splatted through the film's filter, service/render/splat.py) where the samples alone are
expected to be closer to the truth.

On fine, low-noise detail (the tutorials' lego, Gaussian film, 128², 128 spp) the denoiser adds
little, and what it reads — the per-pixel filter-importance-sampled estimates, kept uncorrelated
for it — has ~3× the variance of the splatted image of the same samples (docs/fidelity.md): there
the loop's denoised image scored SMAPE 0.0063 and the splatted raw image of its samples 0.0033,
`mi.render`'s 0.0050. On noisy scenes it is the other way round (tutorials cbox: 0.0201 vs 0.0477).

Each pixel compares two expected errors, both as SMAPE at the networks' exposure (models.exposure;
SMAPE's ε is absolute): e_d, the error network's prediction for the denoised image, and e_r, the
raw image's from its variance — for a normal error of standard deviation σ, E|x − μ| = σ·√(2/π),
so per channel e_r = √(2/π)·σ / (2|r| + ε) (SMAPE's denominator with d ≈ r; eq. 2 of Vogels et
al. 2018). Per pixel both are noisy (correlation with the true error 0.3–0.5 and 0.6–0.8 on
lego and cbox), and the two images' errors are not independent (the same samples), so
inverse-variance weighting per pixel mixed noise into cbox (0.0201 → 0.0256). Their means over a
WINDOW² neighbourhood decide instead, through a steep weight

    α = ē_d^P / (ē_d^P + ē_r^P),   out = (1 − α)·d + α·r

(P = 2 would be inverse-variance weighting; P = 8 is close to picking the better image per
region without a seam). Measured offline on the loop's own images at 128 spp, 128²: lego
0.0063 → 0.0033, cbox 0.0201 → 0.0199, simple 0.0017 → 0.0016 (docs/fidelity.md).

A window mean dilutes one pixel's outlier. A firefly (one rare bright path among a pixel's
samples, the chrome ball's reflections on scenes/dev dof_desk) has a raw expected error tens of
times its neighbours', yet under the mean of 81 it was taken at α ≈ 0.8 where the raw image wins
around it, and three such pixels carried a quarter of dof_desk's relMSE. The other way round, the
edge of a small bright object (scenes/dev point_object) has a predicted denoised error well above
its dark surroundings', which the mean hid. So each error at a pixel counts as at least the pixel's
own estimate ÷ a ratio — the raw one's ÷ RAW_OUTLIER_RATIO, the denoised one's ÷
DENOISED_OUTLIER_RATIO: noise in the per-pixel estimates stays under the ratios, an outlier does not.

The raw pixel's own estimate reads the truth's magnitude from the denoised pixel, √(2/π)·σ / (2|d| + ε),
not from itself: where one rare bright path lifted a raw pixel far above the truth, |r| grows with
σ and caps the pixel's SMAPE estimate at ~0.4, which in a noisy region (window errors 0.1–0.2) is no
outlier. scenes/dev fog_spot at 128², seed 1: a raw pixel of 84 where the truth is 0.11 was taken
whole, final relMSE 9.88 against 0.0054 on the other seeds. The window's mean keeps the SMAPE
estimate over |r|, bounded as SMAPE itself is, so a firefly does not spill its unbounded estimate
onto the 80 neighbours' decision.
"""
from __future__ import annotations

import math

import numpy as np

from models.losses import SMAPE_EPS
from service.render.framebuffer import row_bands

# E|N(0, σ²)| = σ·√(2/π): the mean absolute deviation of a normal error.
MEAN_ABS_PER_SIGMA = math.sqrt(2.0 / math.pi)
# Side of the neighbourhood whose mean errors decide a pixel (5 to 17 measured alike; 1 was worse).
WINDOW = 9
# Steepness of the weight: 2 mixes like inverse-variance weighting, large picks one image.
SHARPNESS = 8
# How far a pixel's own expected error may exceed its window's mean before it counts on its own:
# an outlier, not noise in the estimate. Swept on the loop's saved images of 15 scenes, 3 seeds
# (docs/decisions.md, 'Outliers in the final image's fallback'): the raw ratio alone (4) took
# dof_desk's relMSE from 1.037x to 0.960x of mi.render + OIDN but point_object's from 0.84x to
# 1.37x of mi.render raw; with the denoised ratio 2 beside it, 0.959x and 0.82x (1 hurt cbox).
RAW_OUTLIER_RATIO = 4.0
DENOISED_OUTLIER_RATIO = 2.0


def _cumsum_rows(values: np.ndarray) -> None:
    """np.cumsum(values, axis=0) in place, one whole row at a time: the same additions per column
    in the same order (bitwise equal), ~2 ms at 2 MP where cumsum's strided walk down the columns
    took ~20 ms."""
    for row in range(1, values.shape[0]):
        np.add(values[row - 1], values[row], out=values[row])


def box_mean(values: np.ndarray, size: int = WINDOW) -> np.ndarray:
    """(H, W) mean over each pixel's size² window, the film's edge pixels standing in beyond it
    (separable running sums, float64: a float32 running sum over a 1920-pixel row loses ~1e-5 of
    a window's mean to cancellation). Each pass writes into its padded copy and its difference
    in place: at 2 MP the temporaries cost as much as the sums."""
    radius = size // 2
    out = np.asarray(values, dtype=np.float64)
    for axis in (0, 1):
        pad = [(radius + 1, radius) if a == axis else (0, 0) for a in range(2)]
        padded = np.pad(out, pad, mode="edge")
        np.moveaxis(padded, axis, 0)[0] = 0.0  # the running sum starts at zero
        if axis == 0:
            _cumsum_rows(padded)
        else:
            np.cumsum(padded, axis=1, out=padded)
        sums = np.moveaxis(padded, axis, 0)
        out = np.moveaxis(np.subtract(sums[size:], sums[:-size]), 0, axis)
        out /= size
    return out


def channel_sum(values: np.ndarray) -> np.ndarray:
    """(H, W, 3) → (H, W): the channels added as numpy's sum over the last axis adds them,
    (c0 + c1) + c2, so bitwise the same; that reduction over a length-3 axis took ~23 ms at 2 MP,
    these two adds 2-4 ms."""
    total = values[..., 0] + values[..., 1]
    total += values[..., 2]
    return total


def raw_expected_error(magnitude: np.ndarray, raw_variance: np.ndarray, exposure: float) -> np.ndarray:
    """(H, W) expected SMAPE of the raw image at the networks' exposure: per channel
    √(2/π)·σ / (2|m| + ε), m the image that stands for the truth's magnitude (`magnitude`: the raw
    image for the window's mean, the denoised one for the pixel's own outlier test), the mean over
    channels (as the error map is)."""
    return raw_expected_errors((magnitude,), raw_variance, exposure)[0]


def raw_expected_errors(magnitudes: tuple[np.ndarray, ...], raw_variance: np.ndarray,
                        exposure: float) -> list[np.ndarray]:
    """`raw_expected_error` over each of `magnitudes`, the spread √(2/π)·σ computed once for all.
    float64, by bands of rows, one colour plane at a time in scratch planes that stay in the CPU's
    cache (at 2 MP the (H, W, 3) float64 temporaries' traffic cost as much as the arithmetic). The
    channels are added in `channel_sum`'s order."""
    height, width, channels = raw_variance.shape
    totals = [np.empty((height, width)) for _ in magnitudes]
    for rows in row_bands(height, width):
        shape = (rows.stop - rows.start, width)
        spread, denominator, error = np.empty(shape), np.empty(shape), np.empty(shape)
        for c in range(channels):
            spread[...] = raw_variance[rows, :, c]
            np.maximum(spread, 0.0, out=spread)
            np.sqrt(spread, out=spread)
            spread *= exposure
            spread *= MEAN_ABS_PER_SIGMA
            for magnitude, total in zip(magnitudes, totals):
                denominator[...] = magnitude[rows, :, c]
                np.abs(denominator, out=denominator)
                denominator *= 2.0
                denominator *= exposure
                denominator += SMAPE_EPS
                np.divide(spread, denominator, out=error)
                if c == 0:
                    total[rows] = error
                else:
                    total[rows] += error
    for total in totals:
        total /= channels  # as ndarray.mean divides its sum
    return totals


def raw_weight(denoised_error: np.ndarray, raw_error: np.ndarray, raw_variance: np.ndarray,
               raw_own_error: np.ndarray | None = None) -> np.ndarray:
    """(H, W) α, the raw image's share, from the two error maps' neighbourhood means, each never
    below the pixel's own error ÷ its outlier ratio (a raw firefly keeps the denoised pixel); the
    raw pixel's own error is `raw_own_error` where given (over the denoised magnitude). A raw
    pixel without a variance estimate (every sample agreed, or too few to tell) gets no share: zero
    spread among a few samples is no evidence of zero error (a rare light path can miss them all)."""
    d = box_mean(denoised_error)  # a new array: the steps below write into it and its kin
    np.maximum(d, denoised_error / DENOISED_OUTLIER_RATIO, out=d)
    r = box_mean(raw_error)
    np.maximum(r, (raw_error if raw_own_error is None else raw_own_error) / RAW_OUTLIER_RATIO, out=r)
    # the ratio first: d^8 underflows for small errors; then α = 1 / (1 + min(ratio, 1e6)^P) in place
    alpha = np.divide(r, d, out=np.full_like(d, np.inf), where=d > 0)
    np.minimum(alpha, 1e6, out=alpha)
    np.power(alpha, SHARPNESS, out=alpha)
    alpha += 1.0
    np.divide(1.0, alpha, out=alpha)
    return np.where((channel_sum(raw_variance) > 0) & (d > 0), alpha, 0.0)


def raw_share(raw: np.ndarray, denoised: np.ndarray, raw_variance: np.ndarray, predicted_error: np.ndarray,
              exposure: float) -> np.ndarray:
    """(H, W, 1) α, the raw image's share of the final image, from the raw and the denoised image,
    the raw image's variance of the mean and the error network's (H, W) map of the denoised image;
    `exposure`: the networks' scale of the frame's samples (models.exposure.Exposure.scale). Like
    the error map (predicted once per iteration), it is computed once per iteration, with the
    iteration's denoised image: a λ edit reuses it and pays only `blend`."""
    window_error, own_error = raw_expected_errors((raw, denoised), raw_variance, exposure)
    alpha = raw_weight(predicted_error, window_error, raw_variance, own_error)[..., None]
    return np.where(np.isfinite(alpha), alpha, 0.0).astype(np.float32)  # an unreadable estimate keeps the denoised pixel


def blend(denoised: np.ndarray, raw: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """(H, W, 3) final image (≥ 0): (1 − α)·d + α·r."""
    # ≥ 0 as the denoised image is: a Mitchell film's negative lobes can make a raw pixel negative.
    # In place in one array (d + α·(r − d), the same operations; IEEE addition commutes).
    out = np.subtract(raw, denoised, dtype=np.result_type(raw, denoised, alpha))
    out *= alpha
    out += denoised
    np.maximum(out, 0.0, out=out)
    return out.astype(np.float32, copy=False)


def compose_final(denoised: np.ndarray, raw: np.ndarray, raw_variance: np.ndarray, predicted_error: np.ndarray,
                  exposure: float) -> np.ndarray:
    """(H, W, 3) final image from the denoised image and the raw image (`raw_share`, `blend`)."""
    return blend(denoised, raw, raw_share(raw, denoised, raw_variance, predicted_error, exposure))
