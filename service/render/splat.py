"""The raw image users look at: every sample splatted through the film's reconstruction filter.

The per-pixel estimates (filters.py) keep each sample in the pixel it was drawn for, so their
noise is uncorrelated — what the denoisers need. But at equal samples a pixel then averages only
its own samples, where Mitsuba's hdrfilm averages every sample whose filter footprint covers it
(σ ÷ 1.4 for the tent, 1.7 for the Gaussian, 3.1 for Mitchell). This module adds hdrfilm's
estimate from the same samples: pixel q's value is Σ w·L / Σ w over all samples near it.

hdrfilm draws its film positions uniformly, so its weight is just the filter f(x − c_q). Ours
are drawn from the filter of the pixel each sample starts in, at that pixel's own rate n_p, so
the film density of one pass is q(x) = Σ_p n_p · p_p(x) (p_p: the truncated FIS density). The
weight

    w = f(x − c_q) · n_q / q(x)

makes each pass an unbiased (ratio-consistent) estimate of ∫ f L / ∫ f whatever the counts:
E[Σ w·L] = n_q ∫ f(x − c_q) L(x) dx and E[Σ w] = n_q ∫ f, so passes add up weighted by the
pixel's own count in each. For a tent under a uniform count the FIS densities sum to one
(a partition of unity) and w is exactly hdrfilm's f; for the Gaussian and Mitchell and at the
film's border the 1/q(x) removes the ripple and truncation of the sampling density.

Accumulated per pixel, on the device inside the trace kernel (one dr.scatter_reduce per tap and
channel, no per-sample host round trip): Σw, Σw·L, Σw²·L, Σw²·L², Σw². FrameBuffer.raw and
raw_variance turn them into the estimate R = Σw·L / Σw and the ratio estimator's variance
Σw²·(L − R)² / (Σw)² — every term carries w², so a negative Mitchell lobe adds variance
instead of cancelling it (a signed Σw·L² can make the spread negative or arbitrarily large).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from service.render.filters import PixelFilter
from service.render.framebuffer import SPLAT_CHANNELS as CHANNELS


class FilmSplat:
    """Device-side sums of one render call's samples splatted through the film's filter."""

    def __init__(self, mi, pixel_filter: PixelFilter, counts: np.ndarray):
        self.mi = mi
        self.filter = pixel_filter
        self.height, self.width = counts.shape
        self.channels = CHANNELS
        # One sums array for the whole film, kept on the device across chunks: the taps of a
        # chunk reach beyond its own pixel range, and only one kernel per film size is built.
        # Float64: a pixel gathers samples from ~16 source pixels that different threads add in
        # a varying order, and the variance is a difference of these sums. In float32 two runs of
        # one seed differed by up to 1e-5 relative in raw_variance (1.4e-6 in raw), what a job
        # shared between workers may differ by (tests/service/test_ray_workers.py); in float64
        # they were bit-identical, at no measurable cost.
        self.sums = dr.zeros(mi.Float64, self.height * self.width * self.channels)
        self.counts = mi.Float(np.asarray(counts, dtype=np.float32).ravel())

    def _axis(self, coordinate, size: int, tables):
        """Per tap along one axis: pixel index, whether it is on the film, filter value f and
        the FIS density of that pixel's samples at `coordinate`."""
        mi, pf = self.mi, self.filter
        first = mi.Int32(dr.floor(coordinate - 0.5 - pf.radius)) + 1
        taps = []
        for t in range(pf.taps):
            index = first + t
            inside = (index >= 0) & (index < size)
            clamped = mi.UInt32(dr.clip(index, 0, size - 1))
            distance = coordinate - (mi.Float(index) + 0.5)
            value = dr.select(inside, pf.value(distance), 0.0)
            density = dr.select(inside, pf.density(distance, clamped, tables), 0.0)
            taps.append((clamped, inside, value, density))
        return taps

    def add(self, position, radiance) -> None:
        """Splat one chunk's samples: film `position` in pixels, `radiance` (Color3f, the
        sample's value before any FIS weight, non-finite samples already zeroed)."""
        mi, pf = self.mi, self.filter
        columns = self._axis(position.x, self.width, pf.columns)
        rows = self._axis(position.y, self.height, pf.rows)
        taps, density = [], mi.Float(0.0)
        for row, row_in, fy, py in rows:
            for column, column_in, fx, px in columns:
                index = row * self.width + column
                n = dr.gather(mi.Float, self.counts, index, row_in & column_in)
                density += n * px * py
                taps.append((index, fx * fy * n, row_in & column_in))
        inverse = dr.select(density > 0, dr.rcp(density), 0.0)
        square = dr.square(radiance)
        for index, weighted_count, inside in taps:
            w = weighted_count * inverse
            active = inside & (w != 0)
            w2 = w * w
            values = [w, w * radiance[0], w * radiance[1], w * radiance[2],
                      w2 * radiance[0], w2 * radiance[1], w2 * radiance[2],
                      w2 * square[0], w2 * square[1], w2 * square[2], w2]
            base = index * self.channels
            for c, value in enumerate(values):
                dr.scatter_reduce(dr.ReduceOp.Add, self.sums, mi.Float64(value), base + c, active)

    def host(self) -> np.ndarray:
        """(H, W, channels) float64 sums, read back once per render call."""
        return np.asarray(self.sums, dtype=np.float64).reshape(self.height, self.width, self.channels)
