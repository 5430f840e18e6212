from dataclasses import replace

import torch

from models.denoiser import Denoiser
from models.energy import GAIN_RANGE, conserve_energy, sample_energy
from tests.models.conftest import TINY, make_frame


def noisy_image(variance: float, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    color = torch.rand(2, 3, 32, 32, generator=g) + 0.5
    return color, torch.full_like(color, variance)


def test_a_darkened_image_gets_the_samples_total_back_when_the_samples_know_it():
    color, variance = noisy_image(1e-8)
    mean, rse = sample_energy(color, variance)
    assert (rse < 1e-4).all()
    out = conserve_energy(0.95 * color, mean, rse, tolerance=0.01)
    torch.testing.assert_close(out.mean((1, 2, 3)), color.mean((1, 2, 3)), rtol=1e-5, atol=0)


def test_a_total_the_samples_barely_know_leaves_the_denoisers_energy():
    color, variance = noisy_image(10.0)            # rse ≫ τ: a firefly-dominated total
    mean, rse = sample_energy(color, variance)
    darker = 0.95 * color
    out = conserve_energy(darker, mean, rse, tolerance=0.01)
    assert (out.mean((1, 2, 3)) / darker.mean((1, 2, 3)) - 1).abs().max() < 1e-3


def test_the_trust_follows_the_inverse_variance_weight():
    color, variance = noisy_image(0.0)
    mean, _ = sample_energy(color, variance)
    rse = torch.full((2,), 0.01)                   # rse = τ → k = 1/2: half way
    out = conserve_energy(0.9 * color, mean, rse, tolerance=0.01)
    torch.testing.assert_close(out.mean((1, 2, 3)) / (0.9 * color.mean((1, 2, 3))), torch.full((2,), (1 + 1 / 0.9) / 2))


def test_the_gain_is_bounded_and_a_black_image_stays_black():
    color, variance = noisy_image(0.0)
    mean, rse = sample_energy(color, variance)
    out = conserve_energy(0.1 * color, mean, rse, tolerance=0.01)
    torch.testing.assert_close(out, 0.1 * color * GAIN_RANGE[1])
    black = conserve_energy(torch.zeros_like(color), mean, rse, tolerance=0.01)
    assert torch.equal(black, torch.zeros_like(color))


@torch.no_grad()
def test_the_denoiser_with_an_energy_tolerance_keeps_the_samples_mean_radiance():
    frame = make_frame(16, 16)
    frame.variance.fill_(1e-9)
    frame.albedo.fill_(1.0)     # the untrained kernels then stay within 1 % of the samples' mean (inside GAIN_RANGE)
    frame.color[..., 5, 7] = 20.0   # a firefly: the compositor's floor and cap move energy, so the plain mean drifts
    window = [frame]
    plain = Denoiser(replace(TINY, temporal=False)).eval()
    conserving = Denoiser(replace(TINY, temporal=False, energy_tolerance=0.01)).eval()
    conserving.load_state_dict(plain.state_dict())
    assert plain.prepare(window, 0).energy is None
    out = conserving(window, 0, 4.0)
    torch.testing.assert_close(out.mean(), frame.color.mean(), rtol=1e-5, atol=0)
    before = plain(window, 0, 4.0)
    assert not torch.allclose(before.mean(), frame.color.mean(), rtol=1e-3)
    torch.testing.assert_close(out / out.mean(), before / before.mean())   # one factor, the picture unchanged
