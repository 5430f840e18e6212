"""Temporal accumulation: how a single-frame denoiser uses a window of frames.

A network trained on single frames (`DenoiserConfig.temporal=False`) has no temporal extractor
to weigh neighbours with, but a sequence still holds more samples of each surface than the
center frame alone. `accumulate_window` reprojects every neighbour onto the center frame along
the motion vectors (models.warp) and pools, per pixel, the samples of the neighbours that show
the same thing there: the pooled sample mean

    c̄ = Σ_j n_j c_j / Σ_j n_j,   Var[c̄] = Σ_j n_j² Var[c_j] / (Σ_j n_j)²,   n̄ = Σ_j n_j

over the center (always in) and every consistent neighbour j, n_j its samples per pixel. On a
still sequence this is exactly the render of all the window's samples, so consecutive outputs
share most of their inputs and flicker less; the center frame's own albedo, normal and depth
stay the guides. A neighbour pixel is left out where the reprojection fell off screen, where its
albedo, normal or depth differ from the center's (a disocclusion: another surface), or where its
radiance differs from the center's by more than the noise of both explains (lighting changed:
a moving light, a shadow passing) — the rejection tests of temporal accumulation in real-time
denoisers (Schied et al. 2017, SVGF §4.1), with the rendered variance as the noise scale.
Every output pixel stays a convex combination of real samples.
"""
from __future__ import annotations

import torch
from torch import Tensor

from models.frames import FrameTensors
from models.warp import flow_to_center, warp

# A neighbour's mean counts as the same signal when it lies within this many standard errors of
# the difference (√(Var c_j + Var c_c)) of the center's, per channel; 4σ rejects independent
# Gaussian noise about once in 16 000 pixels.
RADIANCE_SIGMAS = 4.0
RADIANCE_RELATIVE = 0.02     # plus 2 % of the pair's mean: a variance estimate of few samples runs low
ALBEDO_TOLERANCE = 0.1       # per channel, absolute (albedo lies in [0, 1])
NORMAL_TOLERANCE = 0.25      # Euclidean distance of the two normals (≈ 14° between unit vectors)
DEPTH_RELATIVE = 0.05        # |Δ depth| ≤ 5 % of the larger depth
_FIELDS = ("color", "variance", "albedo", "normal", "depth")


def consistent_pixels(center: FrameTensors, other: FrameTensors) -> Tensor:
    """(N,1,H,W) bool: where `other` (already aligned with `center`) shows the same surface
    under the same light, within the noise of both."""
    diff = (other.color - center.color).abs()
    noise = RADIANCE_SIGMAS * (other.variance.clamp_min(0) + center.variance.clamp_min(0)).sqrt()
    scale = RADIANCE_RELATIVE * 0.5 * (other.color.abs() + center.color.abs()) + 1e-6
    same_light = (diff <= noise + scale).all(dim=1, keepdim=True)
    same_albedo = ((other.albedo - center.albedo).abs() <= ALBEDO_TOLERANCE).all(dim=1, keepdim=True)
    same_normal = (other.normal - center.normal).norm(dim=1, keepdim=True) <= NORMAL_TOLERANCE
    larger = torch.maximum(other.depth.abs(), center.depth.abs())
    same_depth = (other.depth - center.depth).abs() <= DEPTH_RELATIVE * larger + 1e-6
    return same_light & same_albedo & same_normal & same_depth


def aligned_to_center(window: list[FrameTensors], center: int, j: int) -> tuple[FrameTensors, Tensor]:
    """Frame j reprojected onto the center frame, and where that reprojection is valid (N,1,H,W).
    A window without motion vectors is still: frames are aligned as they are."""
    frame = window[j]
    flow, valid = flow_to_center([f.motion for f in window], center, j)
    if flow is None:
        return frame, torch.ones_like(frame.depth, dtype=torch.bool)
    sizes = [getattr(frame, name).shape[1] for name in _FIELDS]
    stacked = torch.cat([getattr(frame, name) for name in _FIELDS] + ([frame.spp] if frame.spp is not None else []), 1)
    warped, on_screen = warp(stacked, flow)
    parts = list(torch.split(warped, sizes + ([1] if frame.spp is not None else []), dim=1))
    fields = dict(zip(_FIELDS, parts))
    aligned = FrameTensors(**fields, motion=None, spp=parts[-1] if frame.spp is not None else None)
    return aligned, (valid * on_screen) > 0.5


def accumulate_window(window: list[FrameTensors], center: int) -> FrameTensors:
    """The center frame with the samples of its window's consistent neighbours pooled in (see
    the module docstring); a one-frame window comes back unchanged. Frames must be sanitised
    (finite) and of one size; a frame without a count map counts as one unit per pixel."""
    target = window[center]
    if len(window) == 1:
        return target

    def counts(frame: FrameTensors) -> Tensor:
        return frame.spp if frame.spp is not None else torch.ones_like(frame.depth)

    total = counts(target).clone()
    color_sum = target.color * total
    variance_sum = target.variance * total.square()
    for j in range(len(window)):
        if j == center:
            continue
        other, valid = aligned_to_center(window, center, j)
        weight = counts(other) * (valid & consistent_pixels(target, other))
        total += weight
        color_sum += other.color * weight
        variance_sum += other.variance * weight.square()
    safe = total.clamp_min(1e-12)
    return FrameTensors(color=color_sum / safe, variance=variance_sum / safe.square(), albedo=target.albedo,
                        normal=target.normal, depth=target.depth, motion=target.motion,
                        spp=total if target.spp is not None else None)
