"""The final image's fallback towards the raw image reads neighbourhood means of the expected
errors (service/loop/final_image.py); a single raw pixel's outlier — a firefly — must not ride in
on its neighbours' decision, and ordinary noise in the per-pixel estimate must not change it."""
from __future__ import annotations

import numpy as np

from service.loop.final_image import compose_final

H, W = 24, 32
DENOISED, RAW = 1.0, 1.1


def raw_wins_everywhere() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A region where the raw image's expected error (~1e-3) is far below the denoised one's
    prediction (0.02): denoised, raw, raw variance, predicted error."""
    denoised = np.full((H, W, 3), DENOISED, np.float32)
    raw = np.full((H, W, 3), RAW, np.float32)
    variance = np.full((H, W, 3), 1e-5)
    return denoised, raw, variance, np.full((H, W), 0.02)


def test_a_firefly_among_raw_pixels_that_win_keeps_the_denoised_value() -> None:
    denoised, raw, variance, predicted = raw_wins_everywhere()
    # one rare bright path among the pixel's samples: its mean and its spread jump together
    # (dof_desk's chrome-ball reflections: raw 0.33 where the truth is 0.067)
    raw[12, 16], variance[12, 16] = 20.0, 18.0**2
    out = compose_final(denoised, raw, variance, predicted, exposure=1.0)
    assert abs(out[12, 16] - DENOISED).max() < 0.01, out[12, 16]
    # its neighbours keep the raw image: the window's decision is untouched
    np.testing.assert_allclose(out[12, 15], RAW, atol=1e-3)
    np.testing.assert_allclose(out[2, 2], RAW, atol=1e-3)


def test_ordinary_noise_in_the_raw_error_estimate_keeps_the_windows_decision() -> None:
    denoised, raw, _, predicted = raw_wins_everywhere()
    # the raw image's expected error at ~0.3× the denoised one's, and per-pixel estimates of σ
    # off by up to 3× either way (a few samples' spread): noise in the estimate, not outliers
    rng = np.random.default_rng(3)
    sigma = 0.0166 * np.exp(rng.uniform(np.log(1 / 3), np.log(3), size=(H, W, 1)))
    out = compose_final(denoised, raw, np.broadcast_to(sigma**2, (H, W, 3)).copy(), predicted, exposure=1.0)
    np.testing.assert_allclose(out, RAW, atol=1e-3)


def test_a_few_pixels_predicted_far_worse_denoised_than_their_neighbours_take_the_raw_image() -> None:
    # the denoised image wins around them (predicted 0.001 against the raw image's ~0.005), but
    # the edge of a small bright object is predicted 50× worse on a 2×2 block (point_object)
    denoised = np.full((H, W, 3), DENOISED, np.float32)
    raw = np.full((H, W, 3), RAW, np.float32)
    variance = np.full((H, W, 3), 1.92e-4)
    predicted = np.full((H, W), 0.001)
    predicted[10:12, 14:16] = 0.05
    out = compose_final(denoised, raw, variance, predicted, exposure=1.0)
    np.testing.assert_allclose(out[10:12, 14:16], RAW, atol=0.01)
    # their neighbours keep (nearly: the block lifts their window's mean) the denoised image
    np.testing.assert_allclose(out[10, 13], DENOISED, atol=0.01)
    np.testing.assert_allclose(out[2, 2], DENOISED, atol=1e-3)


def test_a_firefly_in_a_noisy_region_keeps_the_denoised_value() -> None:
    # scenes/dev fog_spot, seed 1: in a noisy region both images' expected errors are ~0.1-0.2, and
    # one rare bright path lifted a raw pixel ~700x above the truth (raw 84, truth 0.11). Its
    # expected error must follow σ against the truth's magnitude, not saturate at SMAPE's ~0.4.
    denoised = np.full((H, W, 3), DENOISED, np.float32)
    rng = np.random.default_rng(5)
    raw = (DENOISED * (1 + 0.3 * rng.standard_normal((H, W, 1)))).repeat(3, -1).astype(np.float32)
    variance = np.full((H, W, 3), 0.3**2)   # e_r ≈ 0.12 everywhere, below the denoised prediction
    predicted = np.full((H, W), 0.15)
    raw[12, 16], variance[12, 16] = 700.0, 700.0**2
    out = compose_final(denoised, raw, variance, predicted, exposure=1.0)
    assert abs(out[12, 16] - DENOISED).max() < 0.05, out[12, 16]
    # away from it the window's decision stands: the raw image (its expected error the lower)
    np.testing.assert_allclose(out[2, 2], raw[2, 2], rtol=0.05)
