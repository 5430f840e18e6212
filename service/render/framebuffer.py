"""Per-frame accumulation buffers: what the renderer adds to and every later step reads."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np


# A pixel counts as converged once this many samples all agreed (FrameBuffer.converged); the
# tolerance absorbs float64 rounding of the sums of identical values.
CONVERGED_MIN_SPP = 16
CONVERGED_REL_TOLERANCE = 1e-9
# Columns of the splat sums the renderer adds (service/render/splat.py): Σw, Σw·L, Σw²·L, Σw²·L², Σw².
# Here, not in splat.py, so that reading a buffer never imports Dr.Jit (the CLI's start-up).
WEIGHT, RADIANCE, SQ_RADIANCE, SQ_RADIANCE_SQ, WEIGHT_SQ = 0, slice(1, 4), slice(4, 7), slice(7, 10), 10
SPLAT_CHANNELS = 11
# The raw image's sums, optional (None under the box filter): checkpoints keep them by these names.
SPLAT_ARRAYS = ("splat_weight", "splat_radiance", "splat_sq_radiance", "splat_sq_radiance_sq", "splat_weight_sq")

# Chains of per-pixel operations run over bands of this many pixels: a band's float64 scratch planes
# (256 KiB each) stay in the CPU's cache, where full-film temporaries went out to memory and back
# between every two operations (1.5× faster at 2 MP; the same operations on the same values).
BAND_ELEMENTS = 1 << 15
_MISSING = object()  # FrameBuffer.cached: no value kept yet (None is a value)


def _finite(values: np.ndarray) -> np.ndarray:
    """NaN/±Inf → 0. A running sum that went non-finite (a corrupted or overflowed accumulator;
    the renderer already drops non-finite samples) holds no usable estimate: read it like an
    unsampled pixel, so no layer handed to the networks or written to EXR is non-finite."""
    return np.where(np.isfinite(values), values, 0.0)


def _zero_nonfinite(values: np.ndarray) -> np.ndarray:
    """`_finite` in place, and only when needed (one isfinite pass when all is well)."""
    finite = np.isfinite(values)
    if not finite.all():
        values[~finite] = 0.0
    return values


def row_bands(height: int, width: int) -> Iterator[slice]:
    """Slices of consecutive rows, BAND_ELEMENTS pixels or so each (at least one row)."""
    step = max(1, BAND_ELEMENTS // max(width, 1))
    for first in range(0, height, step):
        yield slice(first, min(first + step, height))


def _window(values: np.ndarray, radius: int, reduce) -> np.ndarray:
    """`reduce` (np.minimum, np.maximum, np.logical_and) over each pixel's (2r+1)² window, as
    two separable passes; the film's edge pixels stand in for what lies beyond it (the filter
    is truncated to the film, so nothing there reaches in). The reductions are idempotent, so
    the window truncated at the edge equals the edge-padded one: shifted in-place reductions
    without the padded copies (~4× less time at 2 MP)."""
    for axis in (0, 1):
        out = values.copy()
        length = values.shape[axis]
        for shift in range(1, min(radius, length - 1) + 1):
            lo = [slice(None)] * values.ndim
            hi = [slice(None)] * values.ndim
            lo[axis], hi[axis] = slice(0, length - shift), slice(shift, length)
            reduce(out[tuple(lo)], values[tuple(hi)], out=out[tuple(lo)])  # the neighbour below/right
            reduce(out[tuple(hi)], values[tuple(lo)], out=out[tuple(hi)])  # the neighbour above/left
        values = out
    return values


def _reach_box(mask: np.ndarray, radius: int) -> tuple[slice, slice]:
    """The bounding box of `mask`'s True pixels grown by `radius` (clipped to the film): every
    pixel a window reduction of the masked pixels reads."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    height, width = mask.shape
    return (slice(max(rows[0] - radius, 0), min(rows[-1] + radius + 1, height)),
            slice(max(cols[0] - radius, 0), min(cols[-1] + radius + 1, width)))


@dataclass
class FrameBuffer:
    """Running sums for one frame, persistent across render calls.

    Radiance is kept as sum and sum of squares in float64 so that the variance of the mean
    stays accurate after many passes. First-hit AOVs are sums too (divided by `spp` on read),
    so they average over the pixel footprint like the radiance does.
    """

    radiance_sum: np.ndarray  # (H, W, 3) float64
    radiance_sq_sum: np.ndarray  # (H, W, 3) float64
    spp: np.ndarray  # (H, W) int64, samples taken so far
    albedo_sum: np.ndarray  # (H, W, 3) float64
    normal_sum: np.ndarray  # (H, W, 3) float64, world-space shading normal
    depth_sum: np.ndarray  # (H, W) float64, first-hit distance (0 on a miss)
    motion_sum: np.ndarray | None = None  # (H, W, 2) float64, pixels to the previous frame
    # Extra channels of integrators that declare AOVs (Mitsuba's `aov` integrator, `moment`…),
    # named as Mitsuba names them (`albedo.R`, `dd.y.T`, …), filtered like the radiance.
    aov_sum: np.ndarray | None = None  # (H, W, len(aov_names)) float64
    aov_names: tuple[str, ...] = ()
    passes: int = 0  # render calls accumulated (seeds are derived from it)
    meta: dict = field(default_factory=dict)
    # How many pixels beyond its own a sample can land: the film filter's reach
    # (service.render.filters.footprint_pixels; 0 for a box). The loop sets it from its scene.
    footprint: int = 0
    # The same samples splatted through the film's filter (service/render/splat.py): the raw
    # image users look at (`raw`). None under the box filter, where the splat is `mean` itself.
    splat_weight: np.ndarray | None = None  # (H, W) Σw
    splat_radiance: np.ndarray | None = None  # (H, W, 3) Σw·L
    splat_sq_radiance: np.ndarray | None = None  # (H, W, 3) Σw²·L
    splat_sq_radiance_sq: np.ndarray | None = None  # (H, W, 3) Σw²·L²
    splat_weight_sq: np.ndarray | None = None  # (H, W) Σw²
    # What is derived from the sums (the mean, the converged mask, the exposure …), kept until the
    # sums change: an iteration reads the mean up to five times and the mask twice (denoise, then
    # allocate), each a full-film pass. Valid for one value of `passes`, which the renderer bumps
    # after adding each pass's samples; code that writes the sums otherwise calls `invalidate()`.
    _derived: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    _derived_pass: int | None = field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def empty(cls, height: int, width: int) -> "FrameBuffer":
        return cls(
            radiance_sum=np.zeros((height, width, 3)),
            radiance_sq_sum=np.zeros((height, width, 3)),
            spp=np.zeros((height, width), dtype=np.int64),
            albedo_sum=np.zeros((height, width, 3)),
            normal_sum=np.zeros((height, width, 3)),
            depth_sum=np.zeros((height, width)),
        )

    @property
    def shape(self) -> tuple[int, int]:
        return self.spp.shape

    def __getstate__(self) -> dict:
        """Pickled (a Ray actor's buffers) without the derived arrays: they are rebuilt on read."""
        return {**self.__dict__, "_derived": {}, "_derived_pass": None}

    def invalidate(self) -> None:
        """Forget every derived array: the sums were written other than by a render pass."""
        self._derived = {}
        self._derived_pass = None

    def cached(self, key: object, compute: Callable[[], object]) -> object:
        """`compute()`, once per pass of samples (see `_derived`). Every reader of the pass shares
        the one array: read it, never write into it. (Not flagged read-only: torch warns on every
        such array handed to torch.from_numpy, e.g. the mean to OIDN.) A new pass replaces the
        dict rather than clearing it, so a reader on another thread (a λ edit) never finds its
        key gone between the lookup and the read."""
        derived = self._derived
        if self._derived_pass != self.passes:
            derived = self._derived = {}
            self._derived_pass = self.passes
        value = derived.get(key, _MISSING)
        if value is _MISSING:
            value = derived[key] = compute()
        return value

    def _counts(self) -> np.ndarray:
        """(H, W) float64 sample counts, 1 where none was taken (whose sums are 0: a division by
        it keeps them 0, the unsampled-pixel rule; `per_sample_into` enforces it)."""
        return self.cached("counts", lambda: np.maximum(self.spp, 1).astype(np.float64))

    def _unsampled(self) -> np.ndarray | None:
        """(H, W) bool, the pixels without a sample; None when every pixel has one (the norm)."""
        def mask() -> np.ndarray | None:
            unsampled = self.spp == 0
            return unsampled if unsampled.any() else None
        return self.cached("unsampled", mask)

    def per_sample_into(self, total: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Σ/n of `total` ((H, W) or (H, W, C) float64 sums) written into `out` (same shape, any
        dtype and strides: a float32 view into a network tensor), 0 where no sample was taken or
        the sum is not finite. One division per channel plane, the cast fused into it: the
        broadcast of the counts over a length-3 last axis ran numpy's inner loop 3 elements at
        a time (~30 ms at 2 MP; this ~10 ms), with the float64 result the same bit for bit."""
        counts = self._counts()
        if total.ndim == 2:
            np.divide(total, counts, out=out, casting="same_kind")
        else:
            for rows in row_bands(*self.shape):  # a band's three planes share its cache lines
                for c in range(total.shape[-1]):
                    np.divide(total[rows, :, c], counts[rows], out=out[rows, :, c], casting="same_kind")
        unsampled = self._unsampled()
        if unsampled is not None:
            out[unsampled] = 0.0
        return _zero_nonfinite(out)

    def _band_mean(self, total: np.ndarray, rows: slice) -> np.ndarray:
        """`per_sample_into` of one band of rows of a (H, W) sum plane, as a new float64 array."""
        mean = np.divide(total, self._counts()[rows])
        unsampled = self._unsampled()
        if unsampled is not None:
            mean[unsampled[rows]] = 0.0
        return _zero_nonfinite(mean)

    def _per_sample(self, total: np.ndarray, dtype=np.float64) -> np.ndarray:
        return self.per_sample_into(total, np.empty(total.shape, dtype=dtype))

    @property
    def mean(self) -> np.ndarray:
        """Monte Carlo estimate of pixel radiance; 0 where no sample was taken. One array per pass
        shared by every reader (`cached`): never write into it."""
        return self.cached("mean", lambda: self._per_sample(self.radiance_sum, np.float32))

    @property
    def variance(self) -> np.ndarray:
        """Variance of the mean: unbiased sample variance / n (0 where n < 2).

        With a filter, a sample is the weighted value w·L (filters.py) and the mean is their
        plain average, so this is the variance of exactly the estimate `mean` reports — it
        includes the spread the filter weights add (none for box, a little for negative lobes).
        """
        return self.variance_into(np.empty(self.radiance_sum.shape, dtype=np.float32))

    def variance_into(self, out: np.ndarray) -> np.ndarray:
        """`variance` written into `out` ((H, W, 3), any dtype and strides), by row bands and one
        channel plane at a time: (Σx² − n·m²) / (n − 1), clipped at 0, / n, where n > 1 — the
        same float64 operations in the same order as the whole-array formula, without its
        full-film temporaries."""
        counts = self._counts()
        for rows in row_bands(*self.shape):
            n = counts[rows]
            fewer = n - 1
            np.maximum(fewer, 1.0, out=fewer)  # n ≤ 1: any finite divisor, the pixel is set to 0 below
            for c in range(out.shape[-1]):
                plane = self._band_mean(self.radiance_sum[rows, :, c], rows)
                np.square(plane, out=plane)
                plane *= n
                np.subtract(self.radiance_sq_sum[rows, :, c], plane, out=plane)
                plane /= fewer
                np.maximum(plane, 0.0, out=plane)
                np.divide(plane, n, out=out[rows, :, c], casting="same_kind")
        single = self.spp <= 1
        if single.any():
            out[single] = 0.0
        return _zero_nonfinite(out)

    def add_splat(self, sums: np.ndarray) -> None:
        """Add one render call's splat sums ((H, W, 11) columns of splat.py)."""
        self.invalidate()
        if self.splat_weight is None:
            # the first sums are the arrays (0 + x is x: no sum of samples is −0): zeros added to
            # took ~0.5 s at 2 MP on 2 cores, their fresh pages faulted in one by one
            for name, columns in zip(SPLAT_ARRAYS, (WEIGHT, RADIANCE, SQ_RADIANCE, SQ_RADIANCE_SQ, WEIGHT_SQ)):
                setattr(self, name, np.array(sums[..., columns], dtype=np.float64, order="C"))
            return
        self.splat_weight += sums[..., WEIGHT]
        self.splat_radiance += sums[..., RADIANCE]
        self.splat_sq_radiance += sums[..., SQ_RADIANCE]
        self.splat_sq_radiance_sq += sums[..., SQ_RADIANCE_SQ]
        self.splat_weight_sq += sums[..., WEIGHT_SQ]

    @property
    def raw(self) -> np.ndarray:
        """The raw image users look at (`noisy` layer, `--no-denoise`): hdrfilm's estimate
        Σw·L / Σw from every sample under the pixel's filter (splat.py); `mean` for the box."""
        return self.raw_and_variance()[0]

    @property
    def raw_variance(self) -> np.ndarray:
        """Variance of `raw`, the ratio estimator's (delta method): Σw²·(L − R)² / (Σw)², times
        n_eff / (n_eff − 1) with n_eff = (Σw)² / Σw² (Kish) — for equal weights exactly the
        unbiased variance of the mean, `variance`. Every term carries w², so negative lobes add
        to it and never cancel; 0 where n_eff ≤ 1, as `variance` is where n < 2. (Dropping
        Σw²·L, i.e. taking the w²-weighted mean to be R, saves 3 of the 11 channels per tap but
        underestimated the variance ~4× at edges: tests/render/test_raw_image.py.)"""
        return self.raw_and_variance()[1]

    def raw_and_variance(self) -> tuple[np.ndarray, np.ndarray]:
        """(`raw`, `raw_variance`), both from one division of the splat sums and kept for the pass
        (`cached`: the final image, the previews and the result read them)."""
        if self.splat_weight is None:
            return self.mean, self.cached("variance", lambda: self.variance)
        return self.cached("raw", self._splat_estimate)

    def _splat_estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(`raw`, `raw_variance`) as float32, by row bands, one colour plane at a time in float64
        (the same operations in the same order as the whole-array formulas in `raw_variance`'s
        docstring, so the same bits, without their full-film temporaries)."""
        raw, variance = np.empty(self.splat_radiance.shape, np.float32), np.empty(self.splat_radiance.shape, np.float32)
        for rows in row_bands(*self.shape):
            weight, weight_sq = self.splat_weight[rows], self.splat_weight_sq[rows]
            covered = weight > 0
            uncovered = None if covered.all() else ~covered
            n_eff = np.divide(weight**2, weight_sq, out=np.zeros_like(weight), where=(weight_sq > 0) & covered)
            scale = np.divide(1.0, weight**2 * (1 - 1 / np.maximum(n_eff, 1.0)), out=np.zeros_like(weight),
                              where=n_eff > 1)
            mean, spread = np.empty(weight.shape), np.empty(weight.shape)
            for c in range(raw.shape[-1]):
                mean.fill(0.0)
                np.divide(self.splat_radiance[rows, :, c], weight, out=mean, where=covered)
                if uncovered is not None:
                    # a pixel no splat reached with positive weight keeps its own samples' estimate
                    mean[uncovered] = self._band_mean(self.radiance_sum[rows, :, c], rows)[uncovered]
                _zero_nonfinite(mean)
                raw[rows, :, c] = mean
                np.multiply(mean, 2, out=spread)
                spread *= self.splat_sq_radiance[rows, :, c]
                np.subtract(self.splat_sq_radiance_sq[rows, :, c], spread, out=spread)
                np.square(mean, out=mean)
                mean *= weight_sq
                spread += mean
                np.maximum(spread, 0.0, out=spread)
                spread *= scale
                variance[rows, :, c] = spread
        return raw, _zero_nonfinite(variance)

    def converged(self, min_spp: int = CONVERGED_MIN_SPP) -> np.ndarray:
        """(H, W) bool: at least `min_spp` samples and every one returned the same value — an
        empty background (every primary ray missed, radiance 0) or a flat emitter seen directly
        (the same non-zero value). The mean is then exact for what the pixel sees, so nothing
        gains from more samples or from filtering it. A surface pixel whose samples were all 0
        does not count: rare light paths (indirect light in a dark corner) can miss 16 times.

        Under a filter wider than the box (`footprint` > 0), a sample drawn for a pixel lands
        anywhere in the filter's reach, so a pixel beside geometry can see only misses in 16
        samples and still have a non-zero expected value (sun_room's sky row above the ground
        under a Gaussian filter: 15 % of it read 0 at 16 spp, the reference 0.024). Such a pixel
        is exact only if every pixel within the reach agreed on the same value too."""
        return self.cached(("converged", min_spp, self.footprint), lambda: self._converged(min_spp, self.footprint))

    def settled(self, min_spp: int = CONVERGED_MIN_SPP) -> np.ndarray:
        """(H, W) bool: `converged`, and its 3×3 neighbours (at least; the filter's reach where
        wider) agreed on the same value too — the pixels the allocator leaves at its floor. Under
        the box a pixel's reach is itself, yet an edge crossing it with a few per cent coverage is
        missed by 16 samples as often as not (point_object, box film, seeds 3 and 5: background
        pixels left at 0 where the truth is 0.016-0.04 doubled the final image's relMSE). Such a
        pixel keeps its exact mean in the image while its samples all agree (`converged`); the
        allocator tops its count up (allocate.edge_top_up) before it trusts the agreement."""
        if self.footprint >= 1:
            return self.converged(min_spp)  # the same reach: computed once
        return self.cached(("settled", min_spp, 1), lambda: self._converged(min_spp, 1))

    def _converged(self, min_spp: int, reach: int) -> np.ndarray:
        """`converged`, by bands of rows and one channel plane at a time; the filter's level test
        only over the box of pixels whose whole reach agreed (none on most films: then it costs
        nothing)."""
        counts = self._counts()
        agreed = (self.spp >= min_spp) & (self.radiance_sum.any(axis=-1) | (self.depth_sum == 0))
        for rows in row_bands(*self.shape):
            for c in range(self.radiance_sum.shape[-1]):
                total, squares = self.radiance_sum[rows, :, c], self.radiance_sq_sum[rows, :, c]
                spread = np.square(total)
                spread /= counts[rows]  # an unsampled pixel: 0 / 1, as the masked division gave 0
                np.subtract(squares, spread, out=spread)
                np.abs(spread, out=spread)
                agreed[rows] &= spread <= CONVERGED_REL_TOLERANCE * squares
        if reach <= 0:
            return agreed
        settled = _window(agreed, reach, np.logical_and)
        if not settled.any():
            return settled
        rows, cols = _reach_box(settled, reach)
        level = np.ones(settled[rows, cols].shape, dtype=bool)
        for c in range(self.radiance_sum.shape[-1]):
            region = self.radiance_sum[rows, cols, c]
            mean = np.zeros(region.shape)
            np.divide(region, counts[rows, cols], out=mean)
            mean[self.spp[rows, cols] == 0] = 0.0
            _zero_nonfinite(mean)
            low, high = _window(mean, reach, np.minimum), _window(mean, reach, np.maximum)
            level &= high - low <= CONVERGED_REL_TOLERANCE * np.abs(high)
        settled[rows, cols] &= level
        return settled

    @property
    def albedo(self) -> np.ndarray:
        return self._per_sample(self.albedo_sum, np.float32)

    @property
    def normal(self) -> np.ndarray:
        return self._per_sample(self.normal_sum, np.float32)

    @property
    def depth(self) -> np.ndarray:
        return self._per_sample(self.depth_sum, np.float32)

    @property
    def motion(self) -> np.ndarray | None:
        """Screen-space motion in pixels: pixel (x, y) was at (x + mx, y + my) one frame earlier."""
        return None if self.motion_sum is None else self._per_sample(self.motion_sum, np.float32)

    @property
    def aovs(self) -> np.ndarray | None:
        """Per-pixel means of the integrator's extra channels (None when it declares none)."""
        return None if self.aov_sum is None else self._per_sample(self.aov_sum, np.float32)

    def aov_layers(self) -> dict[str, np.ndarray]:
        """The integrator's extra channels by Mitsuba's names, for ExrFrame.extra."""
        means = self.aovs
        return {} if means is None else {name: means[..., i] for i, name in enumerate(self.aov_names)}

    def copy(self) -> "FrameBuffer":
        return FrameBuffer(
            radiance_sum=self.radiance_sum.copy(),
            radiance_sq_sum=self.radiance_sq_sum.copy(),
            spp=self.spp.copy(),
            albedo_sum=self.albedo_sum.copy(),
            normal_sum=self.normal_sum.copy(),
            depth_sum=self.depth_sum.copy(),
            motion_sum=None if self.motion_sum is None else self.motion_sum.copy(),
            aov_sum=None if self.aov_sum is None else self.aov_sum.copy(),
            aov_names=self.aov_names,
            passes=self.passes,
            meta=dict(self.meta),
            footprint=self.footprint,
            **{name: None if getattr(self, name) is None else getattr(self, name).copy() for name in SPLAT_ARRAYS},
        )
