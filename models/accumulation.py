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
albedo, normal or depth fall outside what the center's 3×3 neighbourhood shows (a disocclusion:
another surface), or where its radiance differs from the center's by more than the noise of
both explains (lighting changed: a moving light, a shadow passing) — the rejection tests of
temporal accumulation in real-time denoisers (Schied et al. 2017, SVGF §4.1), with the rendered
variance as the noise scale. Every output pixel stays a convex combination of sample means
(bilinear taps included). The rule was chosen on validation material (`python -m
bench.experiments.accumulation_rules`; docs/decisions.md, "`accumulate=False`, removed"):
pooling moved pixels too, and guides tested against the center's 3×3 range, won there.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from models.frames import FrameTensors
from models.warp import flow_to_center, warp

# A neighbour's mean counts as the same signal when it lies within this many standard errors of
# the difference (√(Var c_j + Var c_c)) of the center's, per channel; 4σ rejects independent
# Gaussian noise about once in 16 000 pixels.
RADIANCE_SIGMAS = 4.0
RADIANCE_RELATIVE = 0.02     # plus 2 % of the pair's mean: a variance estimate of few samples runs low
# The guides are pixel means too: where a pixel straddles an edge or a sub-pixel texture their
# value moves with the seed. So, as temporal anti-aliasing clamps history to the current frame's
# 3×3 neighbourhood (Karis 2014), a neighbour's guide must lie within the range the center's
# 3×3 neighbourhood spans, widened by a tolerance; another surface moving in falls outside it.
ALBEDO_TOLERANCE = 0.05      # per channel, absolute (albedo lies in [0, 1])
NORMAL_TOLERANCE = 0.1       # per component (components lie in [-1, 1])
DEPTH_RELATIVE = 0.05        # 5 % beyond the neighbourhood's depth range
_FIELDS = ("color", "variance", "albedo", "normal", "depth")


def neighbourhood_range(x: Tensor) -> tuple[Tensor, Tensor]:
    """Per-channel minimum and maximum over each pixel's 3×3 neighbourhood (edges replicated), as
    two separable 3-tap passes of shifted views (a tenth of max_pool2d's CPU time here)."""
    h, w = x.shape[-2:]
    padded = F.pad(x, (1, 1, 1, 1), mode="replicate")

    def extreme3x3(pick) -> Tensor:
        rows = pick(pick(padded[..., 0:h, :], padded[..., 1:h + 1, :]), padded[..., 2:h + 2, :])
        return pick(pick(rows[..., 0:w], rows[..., 1:w + 1]), rows[..., 2:w + 2])

    return extreme3x3(torch.minimum), extreme3x3(torch.maximum)


def _guides(frame: FrameTensors) -> Tensor:
    return torch.cat([frame.albedo, frame.normal, frame.depth], dim=1)


def guide_bounds(center: FrameTensors) -> tuple[Tensor, Tensor]:
    """The range a neighbour's albedo, normal and depth (7 channels, `_guides` order) must lie in:
    the center's 3×3 range widened by each guide's tolerance. Computed once per window."""
    lo, hi = neighbourhood_range(_guides(center))
    absolute = lo.new_tensor([ALBEDO_TOLERANCE] * 3 + [NORMAL_TOLERANCE] * 3 + [1e-6]).view(1, 7, 1, 1)
    relative = lo.new_tensor([0.0] * 6 + [DEPTH_RELATIVE]).view(1, 7, 1, 1)
    return lo - absolute - relative * lo.abs(), hi + absolute + relative * hi.abs()


def same_light(center: FrameTensors, other: FrameTensors) -> Tensor:
    """(N,1,H,W) bool: every channel of the two means within RADIANCE_SIGMAS standard errors of
    their difference (plus RADIANCE_RELATIVE of their mean) of each other."""
    diff = (other.color - center.color).abs()
    noise = RADIANCE_SIGMAS * (other.variance.clamp_min(0) + center.variance.clamp_min(0)).sqrt()
    scale = RADIANCE_RELATIVE * 0.5 * (other.color.abs() + center.color.abs()) + 1e-6
    return (diff <= noise + scale).all(dim=1, keepdim=True)


def consistent_pixels(center: FrameTensors, other: FrameTensors,
                      bounds: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """(N,1,H,W) bool: where `other` (already aligned with `center`) shows the same surface
    under the same light, within the noise of both. `bounds`: `guide_bounds(center)` if known."""
    lo, hi = bounds if bounds is not None else guide_bounds(center)
    guides = _guides(other)
    return same_light(center, other) & ((guides >= lo) & (guides <= hi)).all(dim=1, keepdim=True)


def aligned_to_center(window: list[FrameTensors], center: int, j: int) -> tuple[FrameTensors, Tensor]:
    """Frame j reprojected onto the center frame along the motion vectors (bilinear; an integer
    shift, a still pixel included, moves values exactly), and where that reprojection is valid
    (N,1,H,W) bool. A window without motion vectors is still: frames are aligned as they are."""
    frame = window[j]
    flow, valid = flow_to_center([f.motion for f in window], center, j)
    if flow is None or not flow.any():                       # nothing moved: no taps to take
        return frame, torch.ones_like(frame.depth, dtype=torch.bool) if flow is None else valid > 0.5
    extra = [frame.spp] if frame.spp is not None else []
    sizes = [getattr(frame, name).shape[1] for name in _FIELDS] + [1] * len(extra)
    warped, on_screen = warp(torch.cat([getattr(frame, name) for name in _FIELDS] + extra, 1), flow)
    parts = torch.split(warped, sizes, dim=1)
    aligned = FrameTensors(**dict(zip(_FIELDS, parts)), spp=parts[-1] if extra else None)
    return aligned, (valid * on_screen) > 0.5


def sample_counts(frame: FrameTensors) -> Tensor:
    """(N,1,H,W) samples per pixel; a frame without a count map counts one unit per pixel."""
    return frame.spp if frame.spp is not None else torch.ones_like(frame.depth)


def pool(target: FrameTensors, neighbours: list[tuple[FrameTensors, Tensor]]) -> FrameTensors:
    """`target` with each (aligned neighbour, mask) pooled in, weighted by its sample counts × the
    mask (bool, or a share in [0, 1]): the module docstring's c̄, Var c̄, n̄. Guides and motion
    stay the target's."""
    total = sample_counts(target).clone()
    color_sum = target.color * total
    variance_sum = target.variance * total.square()
    for other, mask in neighbours:
        weight = sample_counts(other) * mask
        total += weight
        color_sum += other.color * weight
        variance_sum += other.variance * weight.square()
    safe = total.clamp_min(1e-12)
    return FrameTensors(color=color_sum / safe, variance=variance_sum / safe.square(), albedo=target.albedo,
                        normal=target.normal, depth=target.depth, motion=target.motion,
                        spp=total if target.spp is not None else None)


def accumulate_window(window: list[FrameTensors], center: int) -> FrameTensors:
    """The center frame with the samples of its window's consistent neighbour pixels pooled in
    (see the module docstring); a one-frame window comes back unchanged. Frames must be sanitised
    (finite) and of one size."""
    target = window[center]
    if len(window) == 1:
        return target
    bounds, neighbours = guide_bounds(target), []
    for j in range(len(window)):
        if j != center:
            other, valid = aligned_to_center(window, center, j)
            neighbours.append((other, valid & consistent_pixels(target, other, bounds)))
    return pool(target, neighbours)
