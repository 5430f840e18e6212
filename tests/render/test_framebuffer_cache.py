"""FrameBuffer's derived arrays: kept for one pass of samples, renewed when a pass adds samples,
and the same as the definitions they shortcut (service/render/framebuffer.py)."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from service.render.framebuffer import BAND_ELEMENTS, CONVERGED_MIN_SPP, CONVERGED_REL_TOLERANCE, SPLAT_CHANNELS, FrameBuffer
from service.render.renderer import render_samples
from tests.render.cornell import cornell_box

SIZE = 12


@pytest.fixture(scope="module")
def cornell():
    return cornell_box(SIZE, "gaussian")


def expected_mean(buffer: FrameBuffer) -> np.ndarray:
    n = buffer.spp[..., None]
    return np.where(n > 0, buffer.radiance_sum / np.maximum(n, 1), 0.0).astype(np.float32)


def test_the_cached_mean_and_mask_are_renewed_when_a_render_pass_adds_samples(cornell):
    buffer = FrameBuffer.empty(SIZE, SIZE)
    buffer.footprint = 2
    render_samples(cornell, np.full((SIZE, SIZE), 4), buffer, seed=1)
    first, first_mask = buffer.mean, buffer.converged()
    assert buffer.mean is first and buffer.converged() is first_mask  # one array per pass
    counts = np.zeros((SIZE, SIZE), dtype=np.int64)
    counts[:, : SIZE // 2] = CONVERGED_MIN_SPP  # the left half gets enough samples to settle
    render_samples(cornell, counts, buffer, seed=2)
    assert buffer.mean is not first
    np.testing.assert_array_equal(buffer.mean, expected_mean(buffer))
    assert not np.array_equal(buffer.mean, first)
    assert buffer.converged() is not first_mask


def test_hand_written_sums_are_read_after_invalidate():
    buffer = FrameBuffer.empty(2, 3)
    buffer.spp[:] = 2
    buffer.radiance_sum[:] = 1.0
    np.testing.assert_array_equal(buffer.mean, np.full((2, 3, 3), 0.5, dtype=np.float32))
    buffer.radiance_sum[:] = 4.0
    buffer.invalidate()
    np.testing.assert_array_equal(buffer.mean, np.full((2, 3, 3), 2.0, dtype=np.float32))


def test_a_pickled_buffer_carries_no_derived_arrays():
    buffer = FrameBuffer.empty(64, 64)
    buffer.spp[:] = 1
    buffer.mean, buffer.converged()
    copy = pickle.loads(pickle.dumps(buffer))
    assert copy._derived == {} and len(pickle.dumps(buffer)) < len(pickle.dumps(copy)) + 1024
    np.testing.assert_array_equal(copy.mean, buffer.mean)


def test_the_variance_of_the_mean_matches_its_definition():
    rng = np.random.default_rng(3)
    buffer = FrameBuffer.empty(5, 7)
    buffer.spp[:] = rng.integers(0, 6, size=(5, 7))
    samples = [[rng.gamma(2.0, 0.3, size=(n, 3)) for n in row] for row in buffer.spp]
    for (y, x), n in np.ndenumerate(buffer.spp):
        buffer.radiance_sum[y, x] = samples[y][x].sum(axis=0)
        buffer.radiance_sq_sum[y, x] = (samples[y][x] ** 2).sum(axis=0)
    expected = np.zeros((5, 7, 3))
    for (y, x), n in np.ndenumerate(buffer.spp):
        if n > 1:
            expected[y, x] = samples[y][x].var(axis=0, ddof=1) / n
    np.testing.assert_allclose(buffer.variance, expected, rtol=1e-5, atol=1e-12)


def windowed_converged(buffer: FrameBuffer) -> np.ndarray:
    """converged() as its docstring defines it, pixel by pixel: every pixel within the reach agreed
    and all their means are level."""
    n = buffer.spp[..., None]
    mean = np.where(n > 0, buffer.radiance_sum / np.maximum(n, 1), 0.0)
    spread = buffer.radiance_sq_sum - np.where(n > 0, buffer.radiance_sum**2 / np.maximum(n, 1), 0.0)
    same = (np.abs(spread) <= CONVERGED_REL_TOLERANCE * buffer.radiance_sq_sum).all(axis=-1)
    lit, missed = buffer.radiance_sum.any(axis=-1), buffer.depth_sum == 0
    agreed = (buffer.spp >= CONVERGED_MIN_SPP) & same & (lit | missed)
    height, width = buffer.shape
    r = buffer.footprint
    out = np.zeros((height, width), dtype=bool)
    for y in range(height):
        for x in range(width):
            window = (slice(max(y - r, 0), y + r + 1), slice(max(x - r, 0), x + r + 1))
            values = mean[window].reshape(-1, 3)
            level = (values.max(0) - values.min(0) <= CONVERGED_REL_TOLERANCE * np.abs(values.max(0))).all()
            out[y, x] = agreed[window].all() and level
    return out


@pytest.mark.parametrize("footprint", [0, 1, 2, 3])
def test_converged_matches_its_windowed_definition_on_scattered_flat_patches(footprint):
    rng = np.random.default_rng(footprint)
    height, width = 23, 31
    buffer = FrameBuffer.empty(height, width)
    buffer.spp[:] = CONVERGED_MIN_SPP
    level = rng.choice([0.0, 0.25, 2.0], size=(height, width, 1)) * np.ones(3)
    noisy = rng.random((height, width)) < 0.15  # samples that disagree
    buffer.radiance_sum[:] = level * CONVERGED_MIN_SPP
    buffer.radiance_sq_sum[:] = level**2 * CONVERGED_MIN_SPP
    buffer.radiance_sq_sum[noisy] *= 1.1
    buffer.depth_sum[:] = np.where(level[..., 0] == 0, 0.0, 3.0)
    flat = rng.random((height, width)) < 0.5  # large patches of one level, so some windows settle
    buffer.radiance_sum[flat] = 0.25 * CONVERGED_MIN_SPP
    buffer.radiance_sq_sum[flat & ~noisy] = 0.25**2 * CONVERGED_MIN_SPP
    buffer.radiance_sum[:8, :12] = buffer.radiance_sq_sum[:8, :12] = 0.0  # a settled empty corner
    buffer.depth_sum[:8, :12] = 0.0
    buffer.footprint = footprint
    expected = windowed_converged(buffer)
    assert expected.any()
    np.testing.assert_array_equal(buffer.converged(), expected)


def test_a_settled_pixel_sees_the_level_of_an_agreed_neighbour_that_is_not_settled_itself():
    """Row: three misses, a flat emitter, a noisy pixel. Under a tent (reach 1) the third miss is
    settled by agreement (its neighbours all agreed) but not level (the emitter is in its reach);
    the emitter is not settled (the noisy pixel is in its reach). The level test must read
    beyond the settled pixels."""
    n = CONVERGED_MIN_SPP
    buffer = FrameBuffer.empty(3, 5)
    buffer.spp[:] = n
    buffer.radiance_sum[:, 3] = 2.0 * n
    buffer.radiance_sq_sum[:, 3] = 4.0 * n
    buffer.radiance_sum[:, 4] = 0.5 * n
    buffer.radiance_sq_sum[:, 4] = 0.3 * n
    buffer.depth_sum[:, 3:] = 1.0
    buffer.footprint = 1
    np.testing.assert_array_equal(buffer.converged(), np.tile([True, True, False, False, False], (3, 1)))
    np.testing.assert_array_equal(buffer.converged(), windowed_converged(buffer))


def test_row_bands_give_the_whole_film_formulas():
    """A film wider than a band (one row a band) read band by band equals the whole-array
    formulas: the mean, the variance of the mean and the splatted raw image with its variance."""
    rng = np.random.default_rng(11)
    height, width = 4, BAND_ELEMENTS + 77
    buffer = FrameBuffer.empty(height, width)
    buffer.spp[:] = rng.integers(0, 4, size=(height, width))
    n = buffer.spp[..., None].astype(np.float64)
    buffer.radiance_sum[:] = rng.gamma(2.0, 0.3, size=(height, width, 3)) * n
    buffer.radiance_sq_sum[:] = buffer.radiance_sum**2 / np.maximum(n, 1) * rng.uniform(1.0, 2.0, size=(height, width, 3))
    sums = rng.random((height, width, SPLAT_CHANNELS))
    sums[0, :100, 0] = 0.0  # pixels no splat reached: they keep their own samples' mean
    buffer.add_splat(sums)
    mean = np.divide(buffer.radiance_sum, n, out=np.zeros_like(buffer.radiance_sum), where=n > 0)
    variance = np.divide(buffer.radiance_sq_sum - n * mean**2, n - 1, out=np.zeros_like(mean), where=n > 1)
    variance = np.divide(np.maximum(variance, 0.0), n, out=np.zeros_like(mean), where=n > 1)
    w, wsq = buffer.splat_weight[..., None], buffer.splat_weight_sq[..., None]
    raw = np.where(w > 0, np.divide(buffer.splat_radiance, w, out=np.zeros_like(mean), where=w > 0), mean)
    spread = np.maximum(buffer.splat_sq_radiance_sq - 2 * raw * buffer.splat_sq_radiance + raw**2 * wsq, 0.0)
    n_eff = np.divide(w**2, wsq, out=np.zeros_like(w), where=(wsq > 0) & (w > 0))
    raw_variance = spread * np.divide(1.0, w**2 * (1 - 1 / np.maximum(n_eff, 1.0)), out=np.zeros_like(w), where=n_eff > 1)
    np.testing.assert_array_equal(buffer.mean, mean.astype(np.float32))
    np.testing.assert_array_equal(buffer.variance, variance.astype(np.float32))
    np.testing.assert_allclose(buffer.raw, raw.astype(np.float32), rtol=1e-6)
    np.testing.assert_allclose(buffer.raw_variance, raw_variance.astype(np.float32), rtol=1e-5, atol=1e-30)
