"""Per-frame accumulation buffers: what the renderer adds to and every later step reads."""
from __future__ import annotations

from dataclasses import dataclass, field

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

def _finite(values: np.ndarray) -> np.ndarray:
    """NaN/±Inf → 0. A running sum that went non-finite (a corrupted or overflowed accumulator;
    the renderer already drops non-finite samples) holds no usable estimate: read it like an
    unsampled pixel, so no layer handed to the networks or written to EXR is non-finite."""
    return np.where(np.isfinite(values), values, 0.0)


def _window(values: np.ndarray, radius: int, reduce) -> np.ndarray:
    """`reduce` (np.minimum, np.maximum, np.logical_and) over each pixel's (2r+1)² window, as
    two separable passes; the film's edge pixels stand in for what lies beyond it (the filter
    is truncated to the film, so nothing there reaches in)."""
    for axis in (0, 1):
        n = values.shape[axis]
        pad = [(radius, radius) if a == axis else (0, 0) for a in range(values.ndim)]
        padded = np.moveaxis(np.pad(values, pad, mode="edge"), axis, 0)
        out = padded[:n]
        for k in range(1, 2 * radius + 1):
            out = reduce(out, padded[k:k + n])
        values = np.moveaxis(out, 0, axis)
    return values


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

    def _per_sample(self, total: np.ndarray) -> np.ndarray:
        n = self.spp.reshape(self.spp.shape + (1,) * (total.ndim - 2)).astype(np.float64)
        return _finite(np.divide(total, n, out=np.zeros_like(total), where=n > 0))

    @property
    def mean(self) -> np.ndarray:
        """Monte Carlo estimate of pixel radiance; 0 where no sample was taken."""
        return self._per_sample(self.radiance_sum).astype(np.float32)

    @property
    def variance(self) -> np.ndarray:
        """Variance of the mean: unbiased sample variance / n (0 where n < 2).

        With a filter, a sample is the weighted value w·L (filters.py) and the mean is their
        plain average, so this is the variance of exactly the estimate `mean` reports — it
        includes the spread the filter weights add (none for box, a little for negative lobes).
        """
        n = self.spp[..., None].astype(np.float64)
        mean = self._per_sample(self.radiance_sum)
        sample_var = np.divide(
            self.radiance_sq_sum - n * mean**2, n - 1, out=np.zeros_like(mean), where=n > 1
        )
        var_of_mean = np.divide(np.maximum(sample_var, 0.0), n, out=np.zeros_like(mean), where=n > 1)
        return _finite(var_of_mean).astype(np.float32)

    def add_splat(self, sums: np.ndarray) -> None:
        """Add one render call's splat sums ((H, W, 11) columns of splat.py)."""
        if self.splat_weight is None:
            h, w = self.shape
            self.splat_weight, self.splat_weight_sq = np.zeros((h, w)), np.zeros((h, w))
            self.splat_radiance = np.zeros((h, w, 3))
            self.splat_sq_radiance, self.splat_sq_radiance_sq = np.zeros((h, w, 3)), np.zeros((h, w, 3))
        self.splat_weight += sums[..., WEIGHT]
        self.splat_radiance += sums[..., RADIANCE]
        self.splat_sq_radiance += sums[..., SQ_RADIANCE]
        self.splat_sq_radiance_sq += sums[..., SQ_RADIANCE_SQ]
        self.splat_weight_sq += sums[..., WEIGHT_SQ]

    def _splat_mean(self) -> np.ndarray:
        weight = self.splat_weight[..., None]
        mean = np.divide(self.splat_radiance, weight, out=np.zeros_like(self.splat_radiance), where=weight > 0)
        # A pixel no splat reached with positive weight keeps its own samples' estimate (their
        # mean is ~30 ms at 2 MP, so only when such a pixel exists).
        covered = weight > 0
        return _finite(mean if covered.all() else np.where(covered, mean, self._per_sample(self.radiance_sum)))

    @property
    def raw(self) -> np.ndarray:
        """The raw image users look at (`noisy` layer, `--no-denoise`): hdrfilm's estimate
        Σw·L / Σw from every sample under the pixel's filter (splat.py); `mean` for the box."""
        if self.splat_weight is None:
            return self.mean
        return self._splat_mean().astype(np.float32)

    @property
    def raw_variance(self) -> np.ndarray:
        """Variance of `raw`, the ratio estimator's (delta method): Σw²·(L − R)² / (Σw)², times
        n_eff / (n_eff − 1) with n_eff = (Σw)² / Σw² (Kish) — for equal weights exactly the
        unbiased variance of the mean, `variance`. Every term carries w², so negative lobes add
        to it and never cancel; 0 where n_eff ≤ 1, as `variance` is where n < 2. (Dropping
        Σw²·L, i.e. taking the w²-weighted mean to be R, saves 3 of the 11 channels per tap but
        underestimated the variance ~4× at edges: tests/render/test_raw_image.py.)"""
        if self.splat_weight is None:
            return self.variance
        return self._splat_variance(self._splat_mean())

    def raw_and_variance(self) -> tuple[np.ndarray, np.ndarray]:
        """(`raw`, `raw_variance`) from one division of the splat sums (the final image reads
        both once per iteration: ~75 ms saved at 2 MP)."""
        if self.splat_weight is None:
            return self.mean, self.variance
        mean = self._splat_mean()
        return mean.astype(np.float32), self._splat_variance(mean)

    def _splat_variance(self, mean: np.ndarray) -> np.ndarray:
        """`raw_variance` from the splat mean (H, W, 3), in place where the formula allows (the
        same operations in the same order as written out in `raw_variance`'s docstring)."""
        weight, weight_sq = self.splat_weight[..., None], self.splat_weight_sq[..., None]
        spread = 2 * mean
        spread *= self.splat_sq_radiance
        np.subtract(self.splat_sq_radiance_sq, spread, out=spread)
        spread += np.square(mean) * weight_sq
        np.maximum(spread, 0.0, out=spread)
        n_eff = np.divide(weight**2, weight_sq, out=np.zeros_like(weight), where=(weight_sq > 0) & (weight > 0))
        scale = np.divide(1.0, weight**2 * (1 - 1 / np.maximum(n_eff, 1.0)), out=np.zeros_like(weight), where=n_eff > 1)
        spread *= scale
        return _finite(spread).astype(np.float32)

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
        n = self.spp[..., None].astype(np.float64)
        spread = self.radiance_sq_sum - np.divide(self.radiance_sum**2, n, out=np.zeros_like(self.radiance_sum),
                                                  where=n > 0)
        same = (np.abs(spread) <= CONVERGED_REL_TOLERANCE * self.radiance_sq_sum).all(axis=-1)
        lit = self.radiance_sum.any(axis=-1)
        missed = self.depth_sum == 0  # first-hit distance is 0 for a miss
        agreed = (self.spp >= min_spp) & same & (lit | missed)
        if self.footprint <= 0:
            return agreed
        mean = self._per_sample(self.radiance_sum)
        low, high = _window(mean, self.footprint, np.minimum), _window(mean, self.footprint, np.maximum)
        level = (high - low <= CONVERGED_REL_TOLERANCE * np.abs(high)).all(axis=-1)
        return _window(agreed, self.footprint, np.logical_and) & level

    @property
    def albedo(self) -> np.ndarray:
        return self._per_sample(self.albedo_sum).astype(np.float32)

    @property
    def normal(self) -> np.ndarray:
        return self._per_sample(self.normal_sum).astype(np.float32)

    @property
    def depth(self) -> np.ndarray:
        return self._per_sample(self.depth_sum).astype(np.float32)

    @property
    def motion(self) -> np.ndarray | None:
        """Screen-space motion in pixels: pixel (x, y) was at (x + mx, y + my) one frame earlier."""
        return None if self.motion_sum is None else self._per_sample(self.motion_sum).astype(np.float32)

    @property
    def aovs(self) -> np.ndarray | None:
        """Per-pixel means of the integrator's extra channels (None when it declares none)."""
        return None if self.aov_sum is None else self._per_sample(self.aov_sum).astype(np.float32)

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
