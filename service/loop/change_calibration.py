"""How much the denoised image still moves: a reference-free check on the error network's mean.

The error network predicts each pixel's post-denoise SMAPE from one iteration's inputs. Its map
ranks pixels well, but its *mean* misses by up to 2× on scenes unlike its procedural training
data (docs/calibration.md), and that mean is what `--target-error` stops on. The loop sees one
more thing the network does not: each iteration doubles the samples, and the denoised image
moves between iterations by C = mean SMAPE(Dₖ, Dₖ₋₁) — a measure of the error still present
that needs no network and no reference. C alone mixes in how fast the error falls with samples,
which varies from scene to scene, so it is no better on its own; the geometric mean √(P · s·C) of the two is (docs/decisions.md, "The
change between iterations calibrates the mean": on the development suite 9–10 of 12 scenes within
20 % of the true mean at every iteration, against 4–6 for P). s is fitted on the validation scenes
with the network's own output scale (`renderloop bench --calibration --suite val --fit-scale DIR`)
and stored in its checkpoint (ErrorPredictorConfig.change_scale). A job with a target error
splits its first iteration in two halves so that mean has a change too (RenderLoop). Only the
map's scale changes: the allocation, proportional to it, is the same.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from models.losses import SMAPE_EPS


def image_change(previous: np.ndarray, current: np.ndarray) -> float:
    """Mean SMAPE (eq. 2, models.losses.smape) between two (H, W, 3) images; non-finite values count as 0."""
    a, b = (torch.tensor(x, dtype=torch.float64).nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)
            for x in (previous, current))
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {tuple(a.shape)} and {tuple(b.shape)}")
    # models.losses.smape's operations in its order, in place in the two copies: at 2 MP its
    # out-of-place chain allocated ~8 full-size float64 temporaries (~250 ms on 2 cores)
    error = torch.sub(a, b).abs_()
    denominator = a.abs_().add_(b.abs_()).add_(SMAPE_EPS)
    return float(error.div_(denominator).mean())


def calibrated_mean(network_mean: float, change: float, change_scale: float) -> float:
    """√(P · s·C): the network's mean P and the scaled change s·C, weighted equally in log space."""
    return math.sqrt(max(network_mean, 0.0) * change_scale * max(change, 0.0))


def calibrate_by_change(error: np.ndarray, change: float | None, change_scale: float | None) -> np.ndarray:
    """The (H, W) error map rescaled to `calibrated_mean`; unchanged without a change (the first
    iteration, a resumed loop, a λ edit between the two images) or a scale, or when its mean is 0."""
    mean = float(error.mean())
    if change is None or change_scale is None or not math.isfinite(change) or mean <= 0.0:
        return error
    return (error * (calibrated_mean(mean, change, change_scale) / mean)).astype(np.float32)
