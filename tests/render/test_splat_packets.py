"""The raw image's splat sums (service/render/splat.py) written as packets: the same sums as a
straightforward per-sample, per-pixel reference in numpy float64, for uneven and uniform counts,
on the fast path (per-thread copies) and on the per-channel atomics the large films keep."""
from __future__ import annotations

import drjit as dr
import numpy as np
import pytest

from service.render.filters import PixelFilter
from service.render.framebuffer import RADIANCE, SQ_RADIANCE, SQ_RADIANCE_SQ, WEIGHT, WEIGHT_SQ
from tests.render.lane_reference import expand_counts
from service.render.runtime import mitsuba
from service.render.splat import EXPAND_BUDGET_BYTES, FIRST_PACKET, SECOND_PACKET, FilmSplat, reduce_mode

WIDTH, HEIGHT = 9, 7  # small and uneven, so most pixels lie within a filter radius of a border


def filter_and_samples(filter_type: str, counts: np.ndarray, seed: int):
    """The film's PixelFilter and one pass of samples drawn as the renderer draws them: film
    positions from each pixel's filter, and an arbitrary positive RGB value per sample."""
    mi = mitsuba()
    pixel_filter = PixelFilter(mi, mi.load_dict({"type": filter_type}), WIDTH, HEIGHT)
    lanes = expand_counts(counts)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, len(lanes))
    idx = mi.UInt32(lanes)
    position, _ = pixel_filter.sample(sampler, idx % WIDTH, idx // WIDTH)
    radiance = mi.Color3f(4 * sampler.next_1d(), sampler.next_1d(), 0.1 + sampler.next_1d())
    dr.eval(position, radiance)
    return pixel_filter, position, radiance


def axis_terms(pixel_filter: PixelFilter, coordinate: np.ndarray, size: int, axis) -> tuple[np.ndarray, np.ndarray]:
    """(samples, size) filter values f(x − c_i) and FIS densities p_i(x) of every pixel i on one
    axis, written out from their definitions in filters.py (offsets in float32, as on the device)."""
    mi = mitsuba()
    centres = np.arange(size, dtype=np.float32) + np.float32(0.5)
    offset = (coordinate[:, None].astype(np.float32) - centres[None, :]).astype(np.float32)
    flat = offset.ravel()
    value = np.asarray(pixel_filter.rfilter.eval(mi.Float(flat)), dtype=np.float64).reshape(offset.shape)
    value = np.where(np.abs(offset) < pixel_filter.radius, value, 0.0)
    span = np.asarray(axis[1], dtype=np.float64)[None, :]
    if pixel_filter.tent:
        shape = np.maximum(1.0 - np.abs(offset.astype(np.float64)) / pixel_filter.radius, 0.0) / pixel_filter.radius
        return value, shape / span
    k = np.floor((offset + np.float32(pixel_filter.half)) / np.float32(pixel_filter.bin_width)).astype(np.int64)
    inside = (k >= 0) & (k < pixel_filter.bins)
    mass = np.asarray(pixel_filter.mass, dtype=np.float64)[np.clip(k, 0, pixel_filter.bins - 1)]
    return value, np.where(inside, mass / (pixel_filter.bin_width * span), 0.0)


def reference_sums(pixel_filter: PixelFilter, position, radiance, counts: np.ndarray) -> np.ndarray:
    """Σw, Σw·L, Σw²·L, Σw²·L², Σw² per pixel with w = f(x − c_q)·n_q / Σ_p n_p·p_p(x), one
    sample and one pixel at a time in float64 (the module docstring's weight, nothing fused)."""
    x, y = np.asarray(position.x), np.asarray(position.y)
    L = np.stack([np.asarray(radiance[c], dtype=np.float64) for c in range(3)], axis=-1)  # (S, 3)
    fx, px = axis_terms(pixel_filter, x, WIDTH, pixel_filter.columns)
    fy, py = axis_terms(pixel_filter, y, HEIGHT, pixel_filter.rows)
    n = counts.astype(np.float64)
    density = np.einsum("sw,hw,sh->s", px, n, py)
    w = fy[:, :, None] * fx[:, None, :] * n[None] / density[:, None, None]  # (S, H, W)
    sums = np.zeros((HEIGHT, WIDTH, 11))
    sums[..., WEIGHT] = w.sum(0)
    sums[..., RADIANCE] = np.einsum("shw,sc->hwc", w, L)
    sums[..., SQ_RADIANCE] = np.einsum("shw,sc->hwc", w**2, L)
    sums[..., SQ_RADIANCE_SQ] = np.einsum("shw,sc->hwc", w**2, L**2)
    sums[..., WEIGHT_SQ] = (w**2).sum(0)
    return sums


UNEVEN = np.random.default_rng(7).integers(0, 7, (HEIGHT, WIDTH))  # zeros included


@pytest.mark.parametrize("filter_type", ["tent", "gaussian", "mitchell"])
@pytest.mark.parametrize("counts", [UNEVEN, np.full((HEIGHT, WIDTH), 5)], ids=["uneven", "uniform"])
@pytest.mark.parametrize("mode", ["film default", "per-channel atomics"])
def test_packet_splat_sums_match_a_per_sample_reference(filter_type, counts, mode):
    mi = mitsuba()
    pixel_filter, position, radiance = filter_and_samples(filter_type, counts, seed=11)
    splat = FilmSplat(mi, pixel_filter, counts)
    if mode == "per-channel atomics":
        splat.mode = dr.ReduceMode.Local  # what a film beyond EXPAND_BUDGET_BYTES (or CUDA) gets
    splat.add(position, radiance)
    got = splat.host()
    want = reference_sums(pixel_filter, position, radiance, counts)
    assert splat.uniform_count == (counts.min() == counts.max())
    # The device computes weights in float32 (then sums in float64): a few ulp of float32.
    scale = np.abs(want).max(axis=(0, 1))
    np.testing.assert_allclose(got / scale, want / scale, rtol=0, atol=2e-6)
    # every sampled pixel got sums (a pixel's weight carries its own count: none where n = 0)
    assert (want[..., WEIGHT][counts > 0] > 0).all()


def test_small_films_take_the_per_thread_copies_and_huge_ones_keep_the_atomics():
    mi = mitsuba()
    per_pixel = (FIRST_PACKET + SECOND_PACKET) * 8 * max(dr.thread_count(), 1)
    assert reduce_mode(mi, 512 * 512) == dr.ReduceMode.Expand
    assert reduce_mode(mi, EXPAND_BUDGET_BYTES // per_pixel + 1) == dr.ReduceMode.Auto
