"""The λ tail's fast paths (issue 43: a λ edit at 2 MP) against their plain definitions."""
import pytest
import torch
import torch.nn.functional as F

import models.denoiser
from models.denoiser import Denoiser, DenoiserConfig
from models.features import log_transform
from models.pyramid import up
from tests.models.conftest import make_frame

H, W = 12, 16


def shipped_shape_with_random_weights() -> Denoiser:
    """The shipped architecture (candidate, gate, clamp, cap, energy) with a λ module that does
    something: a fresh one has ΔW = 0 and ignores λ."""
    den = Denoiser(DenoiserConfig()).eval()
    with torch.no_grad():
        for module in (den.specialise, den.gate.specialise):
            module.delta.normal_()
    return den


def relative_difference(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(((a - b).abs() / b.abs().clamp_min(1e-6)).max())


def test_a_uniform_lambda_map_gives_the_global_lambdas_image():
    den = shipped_shape_with_random_weights()
    with torch.no_grad():
        cache = den.prepare([make_frame(H, W)], 0, torch.rand(1, 3, H, W))
        global_lambda = den.apply(cache, 4.0)
        uniform_map = den.apply(cache, torch.full((1, 1, H, W), 4.0))
        assert not torch.equal(global_lambda, den.apply(cache, 1.0))   # λ matters here
    assert relative_difference(uniform_map, global_lambda) <= 1e-5


def test_a_uniform_map_takes_the_folded_path_and_a_varying_one_the_per_pixel_path():
    den = shipped_shape_with_random_weights()
    with torch.no_grad():
        cache = den.prepare([make_frame(H, W)], 0, torch.rand(1, 3, H, W))
        assert den._lambda_code(cache, torch.full((1, 1, H, W), 4.0)).shape == (1, 1, 1, 1)
        varying = torch.full((1, 1, H, W), 4.0)
        varying[..., 0, 0] = 5.0
        assert den._lambda_code(cache, varying).shape[-2:] == (H, W)


def test_the_folded_per_pixel_tail_equals_the_plain_per_pixel_definition():
    """A map with one odd pixel runs the per-pixel path; away from that pixel's reach (the
    pyramid spreads it over ≤ 20 px) it agrees with the global λ to float rounding."""
    den = shipped_shape_with_random_weights()
    with torch.no_grad():
        cache = den.prepare([make_frame(32, 40)], 0, torch.rand(1, 3, 32, 40))
        lam = torch.full((1, 1, 32, 40), 4.0)
        lam[..., 0, 0] = 5.0
        mapped, folded = den.apply(cache, lam), den.apply(cache, 4.0)
    assert relative_difference(mapped[..., 24:, 28:], folded[..., 24:, 28:]) <= 1e-5
    assert not torch.equal(mapped[..., :2, :2], folded[..., :2, :2])


def test_a_uniform_map_of_the_wrong_size_is_still_refused():
    den = shipped_shape_with_random_weights()
    with torch.no_grad():
        cache = den.prepare([make_frame(H, W)], 0, torch.rand(1, 3, H, W))
        with pytest.raises(ValueError, match="λ map"):
            den.apply(cache, torch.full((1, 1, H, W + 1), 4.0))


@pytest.mark.parametrize("shape", [(1, 3, 7, 9), (2, 1, 4, 5), (1, 8, 3, 3)])
def test_upsampling_each_channel_alone_is_torchs_bilinear_upsampling(shape):
    x = torch.rand(shape)
    expected = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
    torch.testing.assert_close(up(x), expected, rtol=1e-6, atol=1e-7)


def test_the_compositors_channels_last_alpha_is_the_plain_alpha_cnn():
    den = shipped_shape_with_random_weights()
    fine_low, coarse = torch.rand(1, 3, 10, 14) * 3, torch.rand(1, 3, 10, 14) * 3
    plain = torch.sigmoid(den.composite.alpha(torch.cat([log_transform(fine_low), log_transform(coarse)], 1)))
    with torch.no_grad():
        torch.testing.assert_close(den.composite.blend_weight(fine_low, coarse), plain.detach(), rtol=1e-5, atol=1e-6)


def test_bands_outside_a_painted_rectangle_fold_and_keep_the_per_pixel_image(monkeypatch):
    """Rows of one λ take the folded GEMM band by band; the image is the one the whole level
    gets on the per-pixel path (autograd: one band per level, no folding) to float rounding."""
    den = shipped_shape_with_random_weights()
    lam = torch.ones(1, 1, 32, 40)
    lam[..., 8:14, 10:30] = 6.0
    with torch.no_grad():
        cache = den.prepare([make_frame(32, 40)], 0, torch.rand(1, 3, 32, 40))
    with torch.enable_grad():
        whole = den.apply(cache, lam).detach()
    folds = []
    monkeypatch.setattr("models.denoiser.TILE_PIXELS", 4 * 40)   # 4-row bands at the finest level
    monkeypatch.setattr("models.denoiser.constant_regions", lambda code: None)   # a map of too many rectangles
    real = models.denoiser.folded_if_uniform
    monkeypatch.setattr("models.denoiser.folded_if_uniform", lambda code: folds.append(real(code).shape[-1] == 1) or real(code))
    with torch.no_grad():
        banded = den.apply(cache, lam)
    assert any(folds) and not all(folds)
    assert relative_difference(banded, whole) <= 1e-5


@pytest.mark.parametrize("lam", [4.0, "map"])
def test_the_in_place_inference_tail_is_the_autograd_tail(lam):
    """Candidate clamp and blend, and the compositor's swap, run in place without autograd
    (Denoiser._join_candidate_in_place, ScaleCompositor._swap_in_place); with autograd they run
    as written in models.candidate and the compositor's forward."""
    den = shipped_shape_with_random_weights()
    lam = torch.rand(1, 1, 32, 40) * 9 + 1 if lam == "map" else lam
    with torch.no_grad():
        cache = den.prepare([make_frame(32, 40)], 0, torch.rand(1, 3, 32, 40) * 2)
        in_place = den.apply(cache, lam)
    with torch.enable_grad():
        as_written = den.apply(cache, lam).detach()
    assert relative_difference(in_place, as_written) <= 1e-5


def test_the_lambda_modules_per_pixel_logits_are_its_plain_definition():
    """logits(p) = (W₀ + Σᵣ (sᵣ(λ_p) − sᵣ(1))·ΔWᵣ)·h(p), pixel by pixel (LambdaModule's docstring)."""
    module = shipped_shape_with_random_weights().specialise
    hidden = torch.rand(2, 1, 17, 5, 6)
    hidden[:, :, -1] = 1.0
    code = torch.rand(2, 1, 5, 6)
    with torch.no_grad():
        s = (module.mix(code) - module.mix(torch.zeros(1, 1, 1, 1))).permute(0, 2, 3, 1)     # (N,H,W,rank)
        weight = module.base + torch.einsum("nhwr,rkc->nhwkc", s, module.delta)             # per pixel
        plain = torch.einsum("nhwkc,nchw->nkhw", weight, hidden[:, 0])
        torch.testing.assert_close(module(hidden, code), plain, rtol=1e-5, atol=1e-5)
