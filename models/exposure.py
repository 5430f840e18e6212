"""Exposure: one factor per image that brings any scene into the brightness range the networks
were trained on, and takes their output back out of it.

The networks read log(1+x) of radiance and clamp fireflies at a fixed HDR_MAX (models.features):
neither is scale-invariant, so the same scene in physical units (its light × 10¹⁰) came out
with 0.07 % of its samples' energy. Intel Open Image Denoise auto-exposes its HDR input for the
same reason (its `Autoexposure` op: the image averaged over bins of at most 16×16 pixels, the
mean log2 luminance of the bins above 1e-8, exposure = key 0.18 / 2^mean). We measure the same
statistic E (the geometric mean of the bins' luminance) and move it into [lo, hi]:

    s = 1 if lo ≤ E ≤ hi,   hi / E above,   lo / E below.

A range [lo, hi] as wide as the training scenes' (TRAINED_EXPOSURE) would leave typical scenes
untouched, but inside it the loop is not scale-invariant: the error network predicts SMAPE, whose
ε is absolute, so a dark exposure makes it ignore dark regions and the allocation changes. A
32² scene at 10⁻³ (moved to E = 0.01) ended 7 % worse than at 1 (E = 0.05), 12 seeds each
(docs/models.md, "Exposure"). So lo = hi = EXPOSURE_KEY: every image is seen at one exposure,
as OIDN sees every HDR image at its key. The key lies near the median of the development and
validation scenes (0.017 … 0.34, median ≈ 0.1), where the error network's calibration was fitted.

Radiance is multiplied by s (`Exposure.forward`), variances of radiance by s², and every output
radiance divided by s again (`Exposure.inverse`). s is continuous, not rounded to whole stops:
then a scene at any scale reaches the networks as the same numbers up to float rounding, and the
loop makes the same allocation (with s in powers of two the scales reached the networks up to
½ stop apart, and the loop's SMAPE spread 4.5 % over them). OIDN's bins skip an absolute 1e-8;
ours skip bins below DARK_BIN_FRACTION of the image's mean bin luminance, so E scales exactly
with the image (an absolute threshold drops the dark bins of a scene at 10⁻⁶ and shifts E).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from models.frames import FrameTensors

EXPOSURE_BIN = 16                           # pixels a side: OIDN autoexposure's maxBinSize
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)  # Rec. 709 luminance, as OIDN's
DARK_BIN_FRACTION = 1e-8                    # bins darker than this × the mean bin are left out (OIDN: absolute 1e-8)
# The range of E the training scenes' noisy inputs span (`python -m bench.experiments.exposure_range
# --scenes 97 --size 128`: 97 procedural training scenes, 128², 16 spp: p0 0.0065, p1 0.028,
# p50 0.43, p99 1.04, max 1.26; docs/models.md, "Exposure").
TRAINED_EXPOSURE = (0.0065, 1.26)
EXPOSURE_KEY = 0.1                          # the E every image is moved to (module docstring)
EXPOSURE_LO = EXPOSURE_HI = EXPOSURE_KEY


def exposure_metric(color: Tensor) -> Tensor:
    """(N,3,H,W) linear radiance → (N,) E: the geometric mean of the 16×16 bins' mean luminance
    (bins darker than DARK_BIN_FRACTION × the mean bin skipped); NaN for a black image.
    Non-finite and negative values read as 0 (they are noise, not exposure)."""
    # one float64 copy, written in place (the same operations: at 2 MP on the CPU the three
    # full-size temporaries of the out-of-place chain took ~2/3 of this function's time)
    x = color.detach().to(torch.float64, copy=True)
    x.nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0).clamp_min_(0.0)
    weights = x.new_tensor(LUMINANCE_WEIGHTS).view(1, 3, 1, 1)
    lum = x.mul_(weights).sum(1, keepdim=True)
    bins = F.avg_pool2d(lum, EXPOSURE_BIN, ceil_mode=True).flatten(1)       # edge bins: their own pixels' mean
    floor = DARK_BIN_FRACTION * bins.mean(1, keepdim=True)
    lit = bins > floor
    logs = torch.where(lit, torch.log2(bins.clamp_min(1e-300)), torch.zeros_like(bins))
    count = lit.sum(1)
    mean_log = logs.sum(1) / count.clamp_min(1)
    return torch.where(count > 0, torch.exp2(mean_log), torch.full_like(mean_log, math.nan))


def exposure_scale(metric: Tensor, lo: float = EXPOSURE_LO, hi: float = EXPOSURE_HI) -> Tensor:
    """(N,) E → (N,) s: 1 inside [lo, hi], else the factor that moves E onto the nearest edge;
    1 where E is undefined (a black image has nothing to expose)."""
    ones = torch.ones_like(metric)
    s = metric.clamp(lo, hi) / metric
    return torch.where(torch.isfinite(s) & (s > 0), s, ones)


@dataclass(frozen=True)
class Exposure:
    """The forward/inverse pair for one batch of images: scale (N,1,1,1) float32."""
    scale: Tensor

    @staticmethod
    def of(color: Tensor, lo: float = EXPOSURE_LO, hi: float = EXPOSURE_HI) -> "Exposure":
        """The exposure of an (N,3,H,W) radiance batch (its own statistic E, module docstring)
        that brings E into [lo, hi]."""
        s = exposure_scale(exposure_metric(color), lo, hi)
        return Exposure(s.to(device=color.device, dtype=torch.float32).view(-1, 1, 1, 1))

    @property
    def is_identity(self) -> bool:
        return bool((self.scale == 1.0).all())

    def forward(self, radiance: Tensor) -> Tensor:
        """Radiance (or anything linear in it: a denoised image, a candidate) into the networks' range."""
        return radiance if self.is_identity else radiance * self.scale.to(radiance.dtype)

    def inverse(self, radiance: Tensor) -> Tensor:
        """Out of the networks' range: the inverse of `forward`."""
        return radiance if self.is_identity else radiance / self.scale.to(radiance.dtype)

    def forward_variance(self, variance: Tensor) -> Tensor:
        """A variance of radiance scales with s²."""
        return variance if self.is_identity else variance * (self.scale * self.scale).to(variance.dtype)

    def inverse_variance(self, variance: Tensor) -> Tensor:
        return variance if self.is_identity else variance / (self.scale * self.scale).to(variance.dtype)

    def forward_frame(self, frame: FrameTensors) -> FrameTensors:
        """A frame's radiance and variance into the networks' range; the guides are untouched."""
        return replace(frame, color=self.forward(frame.color), variance=self.forward_variance(frame.variance))

    def inverse_frame(self, frame: FrameTensors) -> FrameTensors:
        return replace(frame, color=self.inverse(frame.color), variance=self.inverse_variance(frame.variance))
