"""Input transforms for the networks, in forward/inverse pairs with named constants.

Vogels et al. 2018 §5 feed the network log(1+color), relative variance, log(1+albedo),
normals and depth, with diffuse radiance demodulated by albedo. We have one radiance buffer,
so the whole radiance is demodulated: texture detail then comes back exactly through the
remodulation and the kernels only have to smooth illumination.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from models.frames import FrameTensors

HDR_MAX = 1e6          # clamp for radiance-like buffers: beyond any real firefly, far below float32 max
MOTION_MAX = 1e4       # pixels; anything larger is off-screen for every supported resolution anyway
ALBEDO_EPS = 1e-2      # demodulation guard: black albedo divides by ε, not 0 (same ε as SMAPE, eq. 2)
REL_VAR_EPS = 1e-2     # relative variance var/(mean²+ε): ε keeps dark pixels from exploding (eq. 2's ε)
SPP_MAX = 2.0 ** 31    # samples per pixel: the frame buffer's count is at most a 32-bit integer
SPP_LOG_SCALE = 16.0   # log2(1 + spp) / 16 reaches 1 at 65 535 spp, so the channel stays in [0, ~2]
DEPTH_EPS = 1e-6       # per-image depth normalisation guard for all-zero (no-hit) depth


# --- sanitising: bad values are replaced and counted, never propagated --------------------

def sanitize(t: Tensor, lo: float = 0.0, hi: float = HDR_MAX) -> tuple[Tensor, int]:
    """NaN/±Inf → 0 (counted), then clamp to [lo, hi] (negative radiance noise → 0 by default)."""
    # A finite sum proves every element finite (one NaN or ±Inf makes the sum NaN or ±Inf) at a
    # tenth of isfinite's cost; a sum that overflows on finite values takes the full path.
    if bool(torch.isfinite(t.sum())):
        return t.clamp(lo, hi), 0
    bad = ~torch.isfinite(t)
    n_bad = int(bad.sum())
    clean = torch.where(bad, torch.zeros((), dtype=t.dtype, device=t.device), t)
    return clean.clamp(lo, hi), n_bad


# Albedo is a reflectance: at most 1. Renderers that estimate it by evaluating a glossy lobe at
# one direction (Mitsuba 3's default eval_diffuse_reflectance on a rough conductor) return the
# lobe's peak instead — up to 55 seen on a Cr surface with roughness 0.05 — and demodulating by
# that, then remodulating with a lens-jittered copy of it, sprinkled sparkles over the result.
_RANGES = {  # buffer → valid range
    "color": (0.0, HDR_MAX), "variance": (0.0, HDR_MAX), "albedo": (0.0, 1.0),
    "normal": (-1.0, 1.0), "depth": (0.0, HDR_MAX), "motion": (-MOTION_MAX, MOTION_MAX),
    "spp": (0.0, SPP_MAX),
}


def sanitize_frame(frame: FrameTensors) -> tuple[FrameTensors, int]:
    """Sanitise every buffer of a frame; returns the clean frame and the total bad-value count."""
    count = [0]

    def clean(name: str, t: Tensor) -> Tensor:
        c, n = sanitize(t.float(), *_RANGES[name])
        count[0] += n
        return c

    return frame.map(clean), count[0]


# --- forward/inverse pairs ----------------------------------------------------------------

def log_transform(x: Tensor) -> Tensor:
    """log(1+x): compresses HDR radiance into a range a CNN can read (Vogels §5)."""
    return torch.log1p(x)


def inverse_log_transform(y: Tensor) -> Tensor:
    return torch.expm1(y)


def demodulate(radiance: Tensor, albedo: Tensor) -> Tensor:
    """radiance / (albedo + ε): strips texture so kernels only smooth illumination."""
    return radiance / (albedo + ALBEDO_EPS)


def remodulate(irradiance: Tensor, albedo: Tensor) -> Tensor:
    """Inverse of demodulate: multiplies the texture back in."""
    return irradiance * (albedo + ALBEDO_EPS)


def demodulation_albedo(albedo: Tensor, floor: float) -> Tensor:
    """The albedo a denoiser divides its filtered radiance by: at least `floor` (0 = the albedo).
    Demodulation is right for light the albedo scales. A camera ray that misses everything sees the
    sky or the environment and has albedo 0 (service/render/renderer.py; specular surfaces get 1),
    and so has a black surface: light the albedo does not scale, which radiance / (albedo + ε)
    amplifies up to 1/ε = 100×. A kernel tap across such an edge then carries that amplified value
    onto a diffuse neighbour. The floor bounds the amplification to 1/floor and stays continuous
    in the albedo."""
    return albedo.clamp_min(floor) if floor > 0 else albedo


def relative_variance(mean: Tensor, variance: Tensor) -> Tensor:
    """var / (mean² + ε): noise level independent of exposure (the one definition: the encoder's
    feature, and through service.loop.allocate.exposed_relative_variance the variance allocator's)."""
    return variance / (mean * mean + REL_VAR_EPS)


def sample_count_feature(spp: Tensor) -> Tensor:
    """log2(1 + spp) / SPP_LOG_SCALE: each doubling of a pixel's samples moves it by one step,
    the way each loop iteration doubles the total (Vogels et al. 2018, §7)."""
    return torch.log2(1.0 + spp) / SPP_LOG_SCALE


def normalize_depth(depth: Tensor) -> Tensor:
    """Depth divided by its per-image maximum, so scene scale does not matter."""
    peak = depth.flatten(1).amax(dim=1).view(-1, 1, 1, 1)
    return depth / (peak + DEPTH_EPS)


# --- encoder inputs ------------------------------------------------------------------------

def path_features(f: FrameTensors) -> list[Tensor]:
    """The 13 encoder input channels for the Mitsuba path tracer from an already sanitised frame,
    as planes: log demodulated radiance, log(1+relative variance), log(1+albedo), normal,
    normalised depth."""
    return [
        log_transform(demodulate(f.color, f.albedo)),
        log_transform(relative_variance(f.color, f.variance)),
        log_transform(f.albedo),
        f.normal,
        normalize_depth(f.depth),
    ]


@dataclass(frozen=True)
class FeatureSet:
    channels: int
    # from a SANITISED frame, the channel groups in order: a network concatenates them with its
    # other inputs in one pass (models.layers.cat_channels_last) rather than building them first
    planes: Callable[[FrameTensors], list[Tensor]]

    def build(self, frame: FrameTensors) -> Tensor:
        """(N, channels, H, W) NCHW."""
        return torch.cat(self.planes(frame), dim=1)


# The encoder inputs of both networks: the renderer's buffers (service.render) are Mitsuba's path
# tracer's, the one render source there is.
PATH_FEATURES = FeatureSet(13, path_features)
