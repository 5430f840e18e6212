import math
from dataclasses import replace

import pytest
import torch

from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.layers import cpu_has_native_bfloat16
from tests.models.conftest import make_frame

# Without the kernels/candidate disagreement (the error network of a denoiser without a candidate;
# that input has its own tests in test_kernel_disagreement.py).
PLAIN_INPUTS = {"disagreement_input": False}


def test_error_predictor_output_is_non_negative_with_right_shape():
    ep = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=6, **PLAIN_INPUTS))
    f = make_frame(5, 7, n=2, spp=16)
    f.color[0, 0, 0, 0] = float("nan")
    out = ep(f, torch.rand(2, 3, 5, 7) * 1e7)
    assert out.shape == (2, 1, 5, 7)
    assert (out >= 0).all() and out.isfinite().all()
    out.mean().backward()
    assert all(p.grad.isfinite().all() for p in ep.parameters())


def test_the_sample_count_changes_the_prediction_and_is_required():
    ep = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, **PLAIN_INPUTS))
    f = make_frame(6, 6)
    denoised = torch.rand(1, 3, 6, 6)
    with pytest.raises(ValueError, match="sample count"):
        ep(f, denoised)
    few = ep(replace(f, spp=torch.full((1, 1, 6, 6), 16.0)), denoised)
    many = ep(replace(f, spp=torch.full((1, 1, 6, 6), 4096.0)), denoised)
    assert not torch.allclose(few, many)


def test_output_scale_multiplies_the_prediction_and_nothing_else():
    torch.manual_seed(0)
    plain = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, output_scale=1.0, **PLAIN_INPUTS))
    scaled = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, output_scale=1.5, **PLAIN_INPUTS))
    scaled.load_state_dict(plain.state_dict())
    f, denoised = make_frame(6, 6, spp=16), torch.rand(1, 3, 6, 6)
    torch.testing.assert_close(scaled(f, denoised), 1.5 * plain(f, denoised))


@torch.no_grad()
def test_bfloat16_trunk_keeps_the_predicted_error_within_a_percent(monkeypatch):
    if not cpu_has_native_bfloat16():
        pytest.skip("this CPU has no native bfloat16: the trunk stays float32")
    ep = ErrorPredictor(ErrorPredictorConfig(width=16, blocks=6, **PLAIN_INPUTS)).eval()
    f = make_frame(32, 32, spp=16)
    denoised = torch.rand(1, 3, 32, 32)
    fast = ep(f, denoised)
    monkeypatch.setattr("models.error_predictor.trunk_in_bfloat16", lambda x: False)
    exact = ep(f, denoised)
    assert fast.dtype == exact.dtype == torch.float32
    assert 0 < ((fast - exact).abs().mean() / exact.mean()) < 0.01
