import pytest
import torch

from models.denoiser import Denoiser
from models.pyramid import down
from models.features import demodulate
from models.training import coarse_levels_loss, denoiser_lambda_loss, denoiser_loss, denoiser_smape
from tests.models.conftest import TINY, make_frame


def window():
    return [make_frame(seed=i) for i in range(3)]


def test_coarse_levels_loss_is_zero_for_the_pooled_reference_and_positive_for_the_noisy_input():
    den = Denoiser(TINY)
    frames, reference = window(), make_frame(seed=7).color
    cache = den.prepare(frames, 1)
    pooled = [demodulate(cache.exposure.forward(reference), cache.albedo)]   # the levels' exposure (models.exposure)
    for _ in range(TINY.levels - 1):
        pooled.append(down(pooled[-1]))
    lam = torch.ones(1, 1, 12, 16)
    assert float(coarse_levels_loss(den, cache, pooled, frames[1].color, reference, lam)) == 0.0
    noisy = [demodulate(cache.exposure.forward(frames[1].color), cache.albedo)]
    for _ in range(TINY.levels - 1):
        noisy.append(down(noisy[-1]))
    assert float(coarse_levels_loss(den, cache, noisy, frames[1].color, reference, lam)) > 0.0


def test_coarse_kernels_keep_learning_when_the_compositor_shuts_them_out():
    """α ≈ 0 (eq. 5) must not starve the coarse levels of gradient: they have a loss of their own."""
    den = Denoiser(TINY)
    with torch.no_grad():
        den.composite.alpha[-1].bias.fill_(-40.0)              # sigmoid(-40): the coarse path is closed
    frames, reference = window(), make_frame(seed=7).color
    cache = den.prepare(frames, 1)
    levels = den.filter_levels(cache, 1.0)
    coarse = levels[-1].detach().requires_grad_(True)
    lam = torch.ones(1, 1, 12, 16)
    composited = den.merge_levels(cache, [*levels[:-1], coarse])
    (grad_through_alpha,) = torch.autograd.grad(((composited - reference) ** 2).mean(), coarse)
    own = coarse_levels_loss(den, cache, [*levels[:-1], coarse], frames[1].color, reference, lam)
    (grad_own,) = torch.autograd.grad(own, coarse)
    assert grad_through_alpha.abs().max() < 1e-12 < grad_own.abs().max()
    assert torch.isfinite(denoiser_loss(den, frames, 1, reference, lam))


def test_lambda_stage_validation_ranks_lambda_modules_that_lambda_one_smape_cannot():
    den = Denoiser(TINY).eval()
    frames, reference = window(), make_frame(seed=7).color
    smape_before = denoiser_smape(den, frames, 1, reference)
    loss_before = denoiser_lambda_loss(den, frames, 1, reference)
    with torch.no_grad():
        torch.nn.init.normal_(den.specialise.delta)
    assert denoiser_smape(den, frames, 1, reference) == smape_before
    assert denoiser_lambda_loss(den, frames, 1, reference) != loss_before
