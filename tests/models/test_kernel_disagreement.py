from dataclasses import replace

import pytest
import torch

from models.denoiser import Denoiser
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.kernel_disagreement import apply_for_error_network, apply_with_kernels_image, kernel_disagreement
from models.training import error_predictor_loss
from tests.models.conftest import TINY, make_frame

CANDIDATE = replace(TINY, temporal=False, oidn_candidate=True)

def test_disagreement_is_zero_where_the_denoisers_agree_and_bounded_where_they_do_not():
    image = torch.rand(1, 3, 12, 9) * 4
    assert kernel_disagreement(image, image).abs().max() == 0
    other = image.clone()
    other[..., 6, 4] = -1e30   # a wild value in one pixel: bounded, and only its 5×5 box moves
    d = kernel_disagreement(image, other)
    assert d.shape == (1, 1, 12, 9) and float(d.max()) <= 1.0 and d[..., 6, 4] > 0
    assert d[..., :3, :].abs().max() == 0
    nan = image.clone()
    nan[..., 0, 0] = float("nan")
    assert bool(kernel_disagreement(image, nan).isfinite().all())


@torch.no_grad()
def test_apply_with_kernels_image_returns_the_denoisers_output_and_a_different_kernels_image():
    denoiser = Denoiser(CANDIDATE).eval()
    frame, candidate = make_frame(16, 16), torch.rand(1, 3, 16, 16)
    cache = denoiser.prepare([frame], 0, candidate)
    output, kernels = apply_with_kernels_image(denoiser, cache, 1.0)
    torch.testing.assert_close(output, denoiser.apply(cache, 1.0))
    assert kernels.shape == output.shape and not torch.allclose(kernels, output)


@torch.no_grad()
def test_apply_for_error_network_computes_the_disagreement_only_when_asked_and_needs_a_candidate():
    denoiser = Denoiser(CANDIDATE).eval()
    frame, candidate = make_frame(16, 16), torch.rand(1, 3, 16, 16)
    cache = denoiser.prepare([frame], 0, candidate)
    image, none = apply_for_error_network(denoiser, cache, candidate, 1.0, False)
    assert none is None
    same, d = apply_for_error_network(denoiser, cache, candidate, 1.0, True)
    torch.testing.assert_close(same, image)
    assert d.shape == (1, 1, 16, 16) and bool((d >= 0).all())
    with pytest.raises(ValueError, match="candidate"):
        apply_for_error_network(denoiser, cache, None, 1.0, True)


def test_an_error_network_reading_the_disagreement_requires_it_and_responds_to_it():
    net = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1))
    frame, denoised = make_frame(8, 8, spp=16), torch.rand(1, 3, 8, 8)
    assert net.reads_disagreement and not ErrorPredictor(ErrorPredictorConfig(width=4, disagreement_input=False)).reads_disagreement
    with pytest.raises(ValueError, match="disagreement"):
        net(frame, denoised)
    agree = net(frame, denoised, torch.zeros(1, 1, 8, 8))
    disagree = net(frame, denoised, torch.full((1, 1, 8, 8), 0.3))
    assert not torch.allclose(agree, disagree)
    assert bool(net(frame, denoised, torch.full((1, 1, 8, 8), float("nan"))).isfinite().all())


def test_error_predictor_loss_with_the_disagreement_input_trains_every_weight():
    denoiser = Denoiser(CANDIDATE).eval()
    net = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1))
    frame, reference, candidate = make_frame(16, 16, spp=16), torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 16)
    loss = error_predictor_loss(net, denoiser, frame, reference, candidate)
    loss.backward()
    assert net.head.weight.grad[:, -1].abs().sum() > 0   # the disagreement channel gets a gradient
    with pytest.raises(ValueError, match="candidate"):
        error_predictor_loss(net, denoiser, frame, reference, None)
