import math
from dataclasses import replace

import pytest
import torch

from models.error_predictor import ErrorPredictor, ErrorPredictorConfig, residual_feature
from models.layers import cpu_has_native_bfloat16
from tests.models.conftest import make_frame


def test_error_predictor_output_is_non_negative_with_right_shape():
    ep = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=6))
    f = make_frame(5, 7, n=2)
    f.color[0, 0, 0, 0] = float("nan")
    out = ep(f, torch.rand(2, 3, 5, 7) * 1e7)
    assert out.shape == (2, 1, 5, 7)
    assert (out >= 0).all() and out.isfinite().all()
    out.mean().backward()
    assert all(p.grad.isfinite().all() for p in ep.parameters())


def test_sample_count_input_changes_the_prediction_and_is_required():
    ep = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, sample_count_input=True))
    f = make_frame(6, 6)
    denoised = torch.rand(1, 3, 6, 6)
    with pytest.raises(ValueError, match="sample count"):
        ep(f, denoised)
    few = ep(replace(f, spp=torch.full((1, 1, 6, 6), 16.0)), denoised)
    many = ep(replace(f, spp=torch.full((1, 1, 6, 6), 4096.0)), denoised)
    assert not torch.allclose(few, many)


def test_output_scale_multiplies_the_prediction_and_nothing_else():
    torch.manual_seed(0)
    plain = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1))
    scaled = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, output_scale=1.5))
    scaled.load_state_dict(plain.state_dict())
    f, denoised = make_frame(6, 6), torch.rand(1, 3, 6, 6)
    torch.testing.assert_close(scaled(f, denoised), 1.5 * plain(f, denoised))


@torch.no_grad()
def test_bfloat16_trunk_keeps_the_predicted_error_within_a_percent(monkeypatch):
    if not cpu_has_native_bfloat16():
        pytest.skip("this CPU has no native bfloat16: the trunk stays float32")
    ep = ErrorPredictor(ErrorPredictorConfig(width=16, blocks=6)).eval()
    f = make_frame(32, 32)
    denoised = torch.rand(1, 3, 32, 32)
    fast = ep(f, denoised)
    monkeypatch.setattr("models.error_predictor.trunk_in_bfloat16", lambda x: False)
    exact = ep(f, denoised)
    assert fast.dtype == exact.dtype == torch.float32
    assert 0 < ((fast - exact).abs().mean() / exact.mean()) < 0.01


def _noisy_flat_texture(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A stripe texture (period 4 px, 0.5 ↔ 1.5), its noisy mean (σ = 0.1) and that mean's variance."""
    g = torch.Generator().manual_seed(seed)
    truth = (0.5 + (torch.arange(64) // 2 % 2).float()).expand(1, 3, 64, 64).clone()
    variance = torch.full_like(truth, 0.01)
    return truth, truth + 0.1 * torch.randn(truth.shape, generator=g), variance


def test_the_residual_test_reads_log_two_where_the_denoiser_removed_only_noise():
    truth, noisy, variance = _noisy_flat_texture()
    feature = residual_feature(replace(make_frame(64, 64), color=noisy, variance=variance), truth)
    assert feature.shape == (1, 1, 64, 64)
    assert abs(feature.mean().item() - math.log(2.0)) < 0.05   # z ≈ 1: what was removed is the noise


def test_the_residual_test_rises_where_the_denoiser_also_removed_detail():
    truth, noisy, variance = _noisy_flat_texture()
    blurred = torch.full_like(truth, 1.0)   # the stripes averaged away: |removed| = 0.5 = 5 σ
    feature = residual_feature(replace(make_frame(64, 64), color=noisy, variance=variance), blurred)
    assert feature.mean().item() > math.log(1.0 + 20.0)   # z ≈ 1 + 25


def test_residual_input_is_one_more_channel_that_changes_the_prediction():
    plain = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1))
    with_residual = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, residual_input=True))
    assert with_residual.input_channels == plain.input_channels + 1
    f = make_frame(8, 8)
    assert not torch.allclose(with_residual(f, f.color), with_residual(f, torch.zeros_like(f.color)))
