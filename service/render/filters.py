"""The film's reconstruction filter by filter importance sampling (Ernst et al. 2006).

Mitsuba's hdrfilm splats every sample into all pixels within the filter radius with weight
f(x)·f(y) (its filters are separable) and divides by the summed weights. With a different
sample count in every pixel that splat would mix pixels sampled at different rates, so instead
each lane draws its offset from the pixel centre from the filter itself and stays in its own
pixel. The expectation is then the filtered image:

    E[w · L(c + o)] = ∫ f(x) f(y) L(c + (x, y)) dx dy / ∫∫ f        with o ~ p ∝ |f(x)|·|f(y)|

for the per-lane weight w = f(o)/(p(o) · ∫f). For non-negative filters w ≈ 1; for filters with
negative lobes (mitchell, catmullrom, lanczos) w ≈ sign(f(x) f(y)) · (∫|f| / ∫f)², the factor
Ernst et al. carry as a sign. We evaluate w exactly from the plugin's own `eval`, so the
tabulated sampling density only has to be positive where f is non-zero, not equal to |f|.

Without `sample_border`, hdrfilm only generates samples inside the film, so a pixel within the
filter radius of the border averages over the film part of its footprint only; we truncate each
axis' distribution to the film for that pixel's row/column, which reproduces exactly that.

The density is piecewise constant on bins whose edges include every half-integer offset, so the
truncation at a film border (always a half-integer from a pixel centre) is a bin edge and the
truncated distribution is a contiguous run of the global table.
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

# Bins per half pixel of offset: 2 × 128 bins per pixel keep f nearly constant per bin, so the
# weights of positive filters stay within a fraction of a percent of 1 (low added variance).
BINS_PER_HALF_PIXEL = 128
# A box of radius 1/2 (+ Mitsuba's epsilon) is the uniform in-pixel offset: no table needed.
BOX_RADIUS = 0.5 + 1e-3


def footprint_pixels(radius: float) -> int:
    """How many pixels beyond its own a sample drawn for one pixel can land (offsets up to the
    filter's radius from the pixel centre): 0 for the box, 1 for the tent, 2 for Mitsuba's
    default Gaussian (radius 2)."""
    return max(0, math.ceil(radius - 0.5 - 1e-6))


class PixelFilter:
    """Draws (film position, weight) per lane for pixel (column, row) of a W×H film."""

    def __init__(self, mi, rfilter, width: int, height: int, sample_border: bool = False):
        self.mi = mi
        self.name = rfilter.class_name()
        self.rfilter = rfilter
        self.uniform = bool(rfilter.is_box_filter()) and rfilter.radius() <= BOX_RADIUS
        if self.uniform:
            return
        self.radius = float(rfilter.radius())
        # Pixels per axis whose filter can cover one film position (centres within the radius).
        self.taps = math.ceil(2.0 * self.radius)
        # The tent's CDF inverts in closed form: no table search (the default film filter of
        # many scenes, and a binary search per axis costs ~10 % of a cheap integrator's pass).
        self.tent = self.name == "TentFilter"
        self.negative_lobes = False
        if self.tent:
            self.columns = self._tent_axis(width, sample_border)
            self.rows = self._tent_axis(height, sample_border)
            return
        self.half = math.ceil(2.0 * self.radius) / 2.0  # table extent, a half-integer
        bins = int(round(2.0 * self.half * 2 * BINS_PER_HALF_PIXEL))
        self.bin_width = 2.0 * self.half / bins
        edges = np.linspace(-self.half, self.half, bins + 1)
        mids = 0.5 * (edges[:-1] + edges[1:])
        f_edges, f_mids = self._eval(edges), self._eval(mids)
        # Simpson's rule per bin: |f| mass (the sampling density) and signed mass (the normaliser).
        abs_mass = self.bin_width * (np.abs(f_edges[:-1]) + 4 * np.abs(f_mids) + np.abs(f_edges[1:])) / 6
        signed_mass = self.bin_width * (f_edges[:-1] + 4 * f_mids + f_edges[1:]) / 6
        abs_cdf = np.concatenate([[0.0], np.cumsum(abs_mass)])
        signed_cdf = np.concatenate([[0.0], np.cumsum(signed_mass)])
        self.bins = bins
        self.negative_lobes = bool((f_mids < 0).any())
        self.cdf = mi.Float(abs_cdf.astype(np.float32))
        self.mass = mi.Float(abs_mass.astype(np.float32))
        self.columns = self._axis(width, abs_cdf, signed_cdf, sample_border)
        self.rows = self._axis(height, abs_cdf, signed_cdf, sample_border)

    def _eval(self, x: np.ndarray) -> np.ndarray:
        values = np.asarray(self.rfilter.eval(self.mi.Float(x.astype(np.float32))), dtype=np.float64)
        return np.where(np.abs(x) <= self.radius, values, 0.0)

    def _axis(self, size: int, abs_cdf: np.ndarray, signed_cdf: np.ndarray, sample_border: bool):
        """Per pixel index along one axis: (cdf at the lower end, |f| mass, |f| mass / f mass)
        of the filter truncated to the film (or not, with sample_border)."""
        centre = np.arange(size) + 0.5
        lo = np.full(size, -self.half) if sample_border else np.maximum(-self.half, -centre)
        hi = np.full(size, self.half) if sample_border else np.minimum(self.half, size - centre)
        k_lo = np.rint((lo + self.half) / self.bin_width).astype(np.int64)
        k_hi = np.rint((hi + self.half) / self.bin_width).astype(np.int64)
        start = abs_cdf[k_lo]
        span = abs_cdf[k_hi] - start
        signed = signed_cdf[k_hi] - signed_cdf[k_lo]
        ratio = np.divide(span, signed, out=np.zeros_like(span), where=signed != 0)
        mi = self.mi
        return mi.Float(start.astype(np.float32)), mi.Float(span.astype(np.float32)), mi.Float(ratio.astype(np.float32))

    def _tent_cdf(self, x: np.ndarray) -> np.ndarray:
        """CDF of f(x) = max(0, 1 − |x|/r) normalised on [−r, r]."""
        t = np.clip(np.asarray(x, dtype=np.float64) / self.radius, -1.0, 1.0)
        return np.where(t < 0, 0.5 * (1 + t) ** 2, 1 - 0.5 * (1 - t) ** 2)

    def _tent_axis(self, size: int, sample_border: bool):
        """Per pixel index along one axis: the tent's CDF at the lower end and the CDF span of
        the filter truncated to the film (or not, with sample_border)."""
        centre = np.arange(size) + 0.5
        lo = np.full(size, -self.radius) if sample_border else np.maximum(-self.radius, -centre)
        hi = np.full(size, self.radius) if sample_border else np.minimum(self.radius, size - centre)
        start = self._tent_cdf(lo)
        span = self._tent_cdf(hi) - start
        return self.mi.Float(start.astype(np.float32)), self.mi.Float(span.astype(np.float32))

    def _tent_offset(self, u, index, axis):
        """One axis of the tent, sampled exactly: the weight f(o) / (p(o) ∫f) is 1, truncated
        or not (the truncated film footprint is also what hdrfilm normalises by)."""
        mi = self.mi
        start, span = (dr.gather(mi.Float, table, index) for table in axis)
        c = dr.clip(start + u * span, 0.0, 1.0)
        t = dr.select(c < 0.5, dr.sqrt(2.0 * c) - 1.0, 1.0 - dr.sqrt(dr.maximum(2.0 * (1.0 - c), 0.0)))
        return t * self.radius

    def _offset(self, u, index, axis):
        """One axis: offset from the pixel centre and its weight f(o) / (p(o) ∫f)."""
        mi = self.mi
        start, span, ratio = (dr.gather(mi.Float, table, index) for table in axis)
        target = start + u * span
        k = mi.math.find_interval(self.bins + 1, lambda i: dr.gather(mi.Float, self.cdf, i) <= target)
        mass = dr.gather(mi.Float, self.mass, k)
        t = dr.clip((target - dr.gather(mi.Float, self.cdf, k)) / dr.maximum(mass, 1e-20), 0.0, 1.0)
        offset = -self.half + (mi.Float(k) + t) * self.bin_width
        # p(o) = mass / (bin_width · span) on the truncated table; ∫f = span / ratio.
        weight = self.rfilter.eval(offset) * self.bin_width * ratio / dr.maximum(mass, 1e-20)
        return offset, dr.select(dr.abs(offset) <= self.radius, weight, 0.0)

    def sample(self, sampler, column, row, u=None):
        """(film position in pixels, weight) for lanes at integer pixel (column, row). `u`: the
        lanes' 2D uniforms when they come stratified (stratified_sequence.py), else drawn from
        `sampler`; the warp below is the same either way, so the weights stay exact."""
        mi = self.mi
        u = sampler.next_2d() if u is None else u
        if self.uniform:
            return mi.Vector2f(mi.Float(column), mi.Float(row)) + u, None
        if self.tent:
            ox, oy = self._tent_offset(u.x, column, self.columns), self._tent_offset(u.y, row, self.rows)
            return mi.Vector2f(mi.Float(column) + 0.5 + ox, mi.Float(row) + 0.5 + oy), None
        ox, wx = self._offset(u.x, column, self.columns)
        oy, wy = self._offset(u.y, row, self.rows)
        position = mi.Vector2f(mi.Float(column) + 0.5 + ox, mi.Float(row) + 0.5 + oy)
        return position, wx * wy

    def value(self, distance):
        """The filter along one axis at `distance` from a pixel centre (0 beyond its radius)."""
        return dr.select(dr.abs(distance) < self.radius, self.rfilter.eval(distance), 0.0)

    def density(self, offset, index, axis):
        """The density (per pixel of offset) with which `sample` draws `offset` along one axis
        for the pixel `index` on that axis: what splat.py divides by so that samples drawn for
        different pixels, at different rates, weigh as if they had been spread uniformly."""
        mi = self.mi
        span = dr.gather(mi.Float, axis[1], index)
        if self.tent:
            shape = dr.maximum(1.0 - dr.abs(offset) / self.radius, 0.0) / self.radius
            return shape / dr.maximum(span, 1e-20)
        k = mi.Int32(dr.floor((offset + self.half) / self.bin_width))
        inside = (k >= 0) & (k < self.bins)
        mass = dr.gather(mi.Float, self.mass, mi.UInt32(dr.clip(k, 0, self.bins - 1)), inside)
        return dr.select(inside, mass / (self.bin_width * dr.maximum(span, 1e-20)), 0.0)
