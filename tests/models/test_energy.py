from dataclasses import replace

import torch

from models.denoiser import Denoiser
from models.energy import (GAIN_RANGE, block_energy, conserve_block_energy, conserve_energy, measure_energy,
                           restore_energy, sample_energy)
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


def half_darkened() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Flat samples of 1 known exactly, and a denoised image that lost 20 % on its left half only."""
    color = torch.ones(1, 3, 32, 32)
    image = color.clone()
    image[..., :16] *= 0.8
    return color, torch.full_like(color, 1e-10), image


def test_block_gains_restore_the_energy_where_it_was_lost_and_leave_the_rest():
    color, variance, image = half_darkened()
    out = conserve_block_energy(image, block_energy(color, variance, 8), tolerance=0.01)
    torch.testing.assert_close(out[..., :12], color[..., :12])    # away from the seam: the samples' level
    torch.testing.assert_close(out[..., 20:], image[..., 20:])    # the right half was right and stays so
    seam_gain = (out / image)[0, 0, 0, 12:20]                    # between the two blocks' gains, falling smoothly
    assert (seam_gain <= 1 / 0.8 + 1e-6).all() and (seam_gain >= 1 - 1e-6).all() and (seam_gain.diff() <= 1e-6).all()
    image_wide = conserve_energy(image, *sample_energy(color, variance), tolerance=0.01)
    assert (image_wide[..., 20:] > 1.05).all()                    # one factor brightens what was right


def test_a_block_whose_samples_are_noisy_keeps_the_images_energy():
    color, variance, image = half_darkened()
    variance[..., :8, :8] = 10.0                                  # one block's total rests on a firefly
    out = conserve_block_energy(image, block_energy(color, variance, 8), tolerance=0.01)
    torch.testing.assert_close(out[..., :4, :4], image[..., :4, :4], rtol=1e-3, atol=0)
    torch.testing.assert_close(out[..., 12:16, :4], color[..., 12:16, :4])   # its neighbours still restored


def test_block_gains_are_bounded_black_blocks_stay_black_and_a_cut_block_counts_its_own_pixels():
    color = torch.ones(1, 3, 20, 20)                              # 20 = 2 whole blocks of 8 and a cut one
    image = 0.1 * color
    image[..., :8, :8] = 0.0
    out = conserve_block_energy(image, block_energy(color, torch.zeros_like(color), 8), tolerance=0.01)
    assert torch.equal(out[..., :4, :4], torch.zeros(1, 3, 4, 4))
    torch.testing.assert_close(out[..., 16:, 16:], image[..., 16:, 16:] * GAIN_RANGE[1])
    assert torch.isfinite(out).all() and out.shape == image.shape


def test_a_zero_tolerance_leaves_the_image_untouched_even_where_the_samples_agree_exactly():
    color = torch.ones(1, 3, 16, 16)
    variance = torch.zeros_like(color)                         # rse 0 everywhere: constant sky
    image = 0.9 * color
    out = restore_energy(image, measure_energy(color, variance, block=8), tolerance=0.0)
    assert torch.equal(out, image)


def test_restore_energy_runs_the_image_wide_factor_then_the_blocks():
    color, variance, image = half_darkened()
    without = restore_energy(image, measure_energy(color, variance), tolerance=0.01)
    torch.testing.assert_close(without, conserve_energy(image, *sample_energy(color, variance), tolerance=0.01))
    with_blocks = restore_energy(image, measure_energy(color, variance, block=8), tolerance=0.01)
    torch.testing.assert_close(with_blocks[..., :12], color[..., :12])
    torch.testing.assert_close(with_blocks[..., 20:], color[..., 20:])


@torch.no_grad()
def test_the_denoiser_with_an_energy_block_puts_the_energy_back_where_its_image_lost_it():
    # gate offset 10: the output is the candidate's image, which lost a fifth on its left half only
    color, variance, candidate = half_darkened()
    frame = make_frame(32, 32, motion=False)
    frame.color.copy_(color)
    frame.variance.copy_(variance)
    config = replace(TINY, temporal=False, oidn_candidate=True, gate_offset=10.0, energy_tolerance=0.01)
    image_wide = Denoiser(config).eval()
    blocks = Denoiser(replace(config, energy_block=8)).eval()
    blocks.load_state_dict(image_wide.state_dict())
    cache = blocks.prepare([frame], 0, candidate)
    assert cache.energy.blocks is not None and cache.energy.blocks.total.shape[-2:] == (4, 4)
    out = blocks.apply(cache)
    torch.testing.assert_close(out[..., :12], color[..., :12], rtol=0.01, atol=0)
    torch.testing.assert_close(out[..., 20:], color[..., 20:], rtol=0.01, atol=0)
    assert (image_wide([frame], 0, 1.0, candidate)[..., 20:] > 1.05).all()   # one factor: the right half too bright
