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

Accumulated per pixel, on the device inside the trace kernel (no per-sample host round trip):
Σw, Σw·L, Σw²·L, Σw²·L², Σw². FrameBuffer.raw and
raw_variance turn them into the estimate R = Σw·L / Σw and the ratio estimator's variance
Σw²·(L − R)² / (Σw)² — every term carries w², so a negative Mitchell lobe adds variance
instead of cancelling it (a signed Σw·L² can make the spread negative or arbitrarily large).

What it costs. A sample touches 4 (tent) or 16 (Gaussian, Mitchell) pixels × 11 sums. Written as
one dr.scatter_reduce per channel, Dr.Jit's LLVM backend resolves each channel's conflicts on its
own: a packet's lanes (one pixel's samples, consecutive) hit up to ~9 different pixels per tap,
and each distinct address is one trip through a compare-reduce-store loop — ~2 µs per sample for
the Gaussian, more than tracing a cornell-box path (docs/decisions.md, "The raw image's splat").
Instead each tap's 11 sums go out as two packets, 8 adjacent float64 (Σw, Σw·L, Σw²·L, Σw²) and 4
(Σw²·L², one unused), which Dr.Jit writes as one vector read-add-store per lane into a per-thread
copy of the array (ReduceMode.Expand): ~10× cheaper (~0.2 µs), the same sums up to the order of
float64 additions. The copies cost (threads × the arrays) of memory, so a film too large for
EXPAND_BUDGET_BYTES keeps the per-channel atomics (and so does CUDA, where Expand does not
exist). A uniform pass (every pixel's count the same, e.g. the first iteration or `--spp N`)
skips the 16 count gathers: n cancels from n_q / Σ_p n_p·p_p(x).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from service.render.filters import PixelFilter
from service.render.framebuffer import (RADIANCE, SPLAT_CHANNELS, SQ_RADIANCE, SQ_RADIANCE_SQ, WEIGHT, WEIGHT_SQ,
                                         FrameBuffer)

# The two packets one tap writes (powers of two: what Dr.Jit's packet scatter takes). The first
# holds Σw, Σw·L (3), Σw²·L (3), Σw²; the second Σw²·L² (3) and one unused slot.
FIRST_PACKET, SECOND_PACKET = 8, 4
# Bytes the per-thread copies of both arrays (ReduceMode.Expand) may take: 2 threads × a 2 MP
# film × 12 float64 is 0.4 GB; a film or a thread pool too large for it keeps the atomics.
EXPAND_BUDGET_BYTES = 1 << 30


def reduce_mode(mi, pixels: int) -> dr.ReduceMode:
    """Expand (per-thread copies, non-atomic packet writes) on the LLVM backend when the copies
    fit EXPAND_BUDGET_BYTES; else Auto (Dr.Jit splits the packets into per-channel atomics)."""
    if dr.backend_v(mi.Float) != dr.JitBackend.LLVM:
        return dr.ReduceMode.Auto
    copies = pixels * (FIRST_PACKET + SECOND_PACKET) * 8 * max(dr.thread_count(), 1)
    return dr.ReduceMode.Expand if copies <= EXPAND_BUDGET_BYTES else dr.ReduceMode.Auto


class FilmSplat:
    """Device-side sums of one render call's samples splatted through the film's filter."""

    def __init__(self, mi, pixel_filter: PixelFilter, counts: np.ndarray):
        self.mi = mi
        self.filter = pixel_filter
        self.height, self.width = counts.shape
        pixels = self.height * self.width
        # Film-sized arrays kept on the device across chunks: the taps of a chunk reach beyond
        # its own pixel range, and only one kernel per film size is built.
        # Float64: a pixel gathers samples from ~16 source pixels that different threads add in
        # a varying order, and the variance is a difference of these sums. In float32 two runs of
        # one seed differed by up to 1e-5 relative in raw_variance (1.4e-6 in raw), what a job
        # shared between workers may differ by (tests/service/test_ray_workers.py); in float64
        # they were bit-identical, at no measurable cost.
        self.first = dr.zeros(mi.Float64, pixels * FIRST_PACKET)
        self.second = dr.zeros(mi.Float64, pixels * SECOND_PACKET)
        self.mode = reduce_mode(mi, pixels)
        counts = np.asarray(counts)
        # A uniform pass needs no counts on the device (see the module docstring).
        self.uniform_count = bool(counts.size) and int(counts.min()) == int(counts.max())
        self.counts = None if self.uniform_count else mi.Float(counts.astype(np.float32).ravel())

    @property
    def sums(self) -> tuple:
        """The device arrays the trace kernel writes (what the renderer evaluates per chunk)."""
        return self.first, self.second

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
                inside = row_in & column_in
                if self.uniform_count:
                    density += px * py
                    taps.append((index, fx * fy, inside))
                else:
                    n = dr.gather(mi.Float, self.counts, index, inside)
                    density += n * px * py
                    taps.append((index, fx * fy * n, inside))
        inverse = dr.select(density > 0, dr.rcp(density), 0.0)
        square = dr.square(radiance)
        for index, weighted_count, inside in taps:
            w = weighted_count * inverse
            active = inside & (w != 0)
            w2 = w * w
            first = [w, w * radiance[0], w * radiance[1], w * radiance[2],
                     w2 * radiance[0], w2 * radiance[1], w2 * radiance[2], w2]
            second = [w2 * square[0], w2 * square[1], w2 * square[2], 0.0]
            dr.scatter_reduce(dr.ReduceOp.Add, self.first, mi.ArrayXf64([mi.Float64(v) for v in first]),
                              index, active, mode=self.mode)
            dr.scatter_reduce(dr.ReduceOp.Add, self.second, mi.ArrayXf64([mi.Float64(v) for v in second]),
                              index, active, mode=self.mode)

    def add_to(self, buffer: FrameBuffer) -> None:
        """Add the render call's splat sums to `buffer`, read back once, straight from the
        packets' columns: building host()'s (H, W, 11) copy first took 73-600 ms a pass at 1080p
        on the 2-core host (a fresh 180 MB array each pass, its pages faulted in) against ~40 ms
        for the adds. A buffer without splat arrays yet (its first pass) gets copies of the
        columns, in framebuffer.py's shapes (what FrameBuffer.add_splat would create)."""
        first = np.asarray(self.first, dtype=np.float64).reshape(self.height, self.width, FIRST_PACKET)
        second = np.asarray(self.second, dtype=np.float64).reshape(self.height, self.width, SECOND_PACKET)
        columns = {"splat_weight": first[..., 0], "splat_radiance": first[..., 1:4],
                   "splat_sq_radiance": first[..., 4:7], "splat_sq_radiance_sq": second[..., 0:3],
                   "splat_weight_sq": first[..., 7]}
        for name, values in columns.items():
            target = getattr(buffer, name)
            if target is None:
                setattr(buffer, name, np.array(values, dtype=np.float64, order="C"))
            else:
                np.add(target, values, out=target)

    def host(self) -> np.ndarray:
        """(H, W, SPLAT_CHANNELS) float64 sums in framebuffer.py's column order, read back once
        per render call."""
        first = np.asarray(self.first, dtype=np.float64).reshape(self.height, self.width, FIRST_PACKET)
        second = np.asarray(self.second, dtype=np.float64).reshape(self.height, self.width, SECOND_PACKET)
        sums = np.empty((self.height, self.width, SPLAT_CHANNELS))
        sums[..., WEIGHT] = first[..., 0]
        sums[..., RADIANCE] = first[..., 1:4]
        sums[..., SQ_RADIANCE] = first[..., 4:7]
        sums[..., WEIGHT_SQ] = first[..., 7]
        sums[..., SQ_RADIANCE_SQ] = second[..., 0:3]
        return sums
