"""The final image's composition (service/loop/final_image.py, FrameBuffer.raw_and_variance) against a
straightforward reference written out here from the formulas in their docstrings, on a small real
render of a Gaussian-filtered scene with the shipped networks: the in-place, shared-division code
of issue 43 (item 3) must compose the same image."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from models.exposure import Exposure
from models.losses import SMAPE_EPS
from models.pretrained import load_networks
from service.loop.final_image import DENOISED_OUTLIER_RATIO, RAW_OUTLIER_RATIO, SHARPNESS, WINDOW, compose_final
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec
from service.loop.tensors import nchw

SCENE = Path(__file__).resolve().parents[2] / "scenes" / "dev" / "dof_desk" / "scene.xml"  # Gaussian film


def reference_raw(buffer) -> tuple[np.ndarray, np.ndarray]:
    """hdrfilm's Σw·L / Σw (the pixel's own mean where no weight landed) and its delta-method
    variance Σw²·(L − R)² / (Σw)² · n_eff / (n_eff − 1), n_eff = (Σw)² / Σw², 0 where n_eff ≤ 1."""
    weight, weight_sq = buffer.splat_weight[..., None], buffer.splat_weight_sq[..., None]
    spp = buffer.spp[..., None]
    own = np.where(spp > 0, buffer.radiance_sum / np.maximum(spp, 1), 0.0)
    raw = np.where(weight > 0, buffer.splat_radiance / np.where(weight > 0, weight, 1.0), own)
    spread = buffer.splat_sq_radiance_sq - 2 * raw * buffer.splat_sq_radiance + raw**2 * weight_sq
    n_eff = np.where((weight > 0) & (weight_sq > 0), weight**2 / np.where(weight_sq > 0, weight_sq, 1.0), 0.0)
    safe = np.where(n_eff > 1, n_eff, 2.0)
    denominator = np.where(n_eff > 1, weight, 1.0) ** 2
    variance = np.where(n_eff > 1, np.maximum(spread, 0.0) / denominator * safe / (safe - 1), 0.0)
    return raw.astype(np.float32), variance.astype(np.float32)


def reference_window_mean(values: np.ndarray) -> np.ndarray:
    """Each pixel's WINDOW² mean, edge pixels repeated beyond the film, by summing shifted copies."""
    r = WINDOW // 2
    padded = np.pad(values.astype(np.float64), r, mode="edge")
    h, w = values.shape
    return sum(padded[dy:dy + h, dx:dx + w] for dy in range(WINDOW) for dx in range(WINDOW)) / WINDOW**2


def reference_final(denoised, raw, variance, predicted, exposure) -> np.ndarray:
    """α = ē_d^P / (ē_d^P + ē_r^P) of the outlier-floored window means (the raw pixel's own floor
    over the denoised magnitude), out = max((1 − α)·d + α·r, 0)."""
    sigma = np.sqrt(np.maximum(variance.astype(np.float64), 0.0)) * exposure
    def expected(magnitude: np.ndarray) -> np.ndarray:
        return (math.sqrt(2 / math.pi) * sigma / (2 * np.abs(magnitude.astype(np.float64)) * exposure + SMAPE_EPS)).mean(-1)

    raw_error, raw_own_error = expected(raw), expected(denoised)
    d = np.maximum(reference_window_mean(predicted), predicted.astype(np.float64) / DENOISED_OUTLIER_RATIO)
    r = np.maximum(reference_window_mean(raw_error), raw_own_error / RAW_OUTLIER_RATIO)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        alpha = 1 / (1 + np.minimum(r / d, 1e6) ** SHARPNESS)
    alpha = np.where((variance.sum(-1) > 0) & (d > 0) & np.isfinite(alpha), alpha, 0.0)[..., None]
    return np.maximum((1 - alpha) * denoised + alpha * raw, 0.0)


@pytest.fixture(scope="module")
def small_run() -> RenderLoop:
    loop = RenderLoop(LoopSpec(scene=str(SCENE), width=48, height=32, spp_first=4, max_iterations=2, seed=1),
                      load_networks())
    list(loop.run())
    return loop


def test_the_raw_image_and_its_variance_match_the_formulas_written_out(small_run) -> None:
    buffer = small_run.state.buffers[0]
    raw, variance = buffer.raw_and_variance()
    expected_raw, expected_variance = reference_raw(buffer)
    np.testing.assert_allclose(raw, expected_raw, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(variance, expected_variance, rtol=1e-5, atol=1e-12)
    np.testing.assert_array_equal(raw, buffer.raw)
    np.testing.assert_array_equal(variance, buffer.raw_variance)


def test_a_pixel_no_splat_reached_keeps_its_own_samples_mean_in_the_raw_image(small_run) -> None:
    buffer = small_run.state.buffers[0].copy()
    for name in ("splat_weight", "splat_radiance", "splat_sq_radiance", "splat_sq_radiance_sq", "splat_weight_sq"):
        getattr(buffer, name)[5:9, 10:20] = 0.0  # as where a sparse first pass landed no weight
    raw, variance = buffer.raw_and_variance()
    expected_raw, expected_variance = reference_raw(buffer)
    np.testing.assert_allclose(raw, expected_raw, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(variance, expected_variance, rtol=1e-5, atol=1e-12)
    own = buffer.radiance_sum[5:9, 10:20] / buffer.spp[5:9, 10:20, None]
    np.testing.assert_allclose(raw[5:9, 10:20], own, rtol=1e-6)


def test_the_loops_final_image_matches_the_reference_composition_to_1e5(small_run) -> None:
    loop = small_run
    buffer, predicted = loop.state.buffers[0], loop.state.error_maps[0]
    denoised = loop.denoised_only()[0]
    exposure = float(Exposure.of(nchw(buffer.mean)).scale.flatten()[0])
    raw, variance = reference_raw(buffer)
    expected = reference_final(denoised, raw, variance, predicted, exposure)
    final = loop.denoised()[0]
    assert 0 < np.mean(np.abs(final - denoised)) and np.isfinite(final).all()  # the composition did something
    np.testing.assert_allclose(final, expected, rtol=1e-5, atol=1e-6 * float(np.abs(expected).max()))
    np.testing.assert_allclose(compose_final(denoised, raw, variance, predicted, exposure), expected,
                               rtol=1e-5, atol=1e-6 * float(np.abs(expected).max()))
