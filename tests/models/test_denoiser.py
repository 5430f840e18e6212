from dataclasses import replace

import pytest
import torch

from models.denoiser import Denoiser, DenoiserConfig, ScaleCompositor
from models.features import ALBEDO_EPS
from models.pyramid import down, up
from models.frames import FrameTensors
from models.layers import cpu_has_native_bfloat16, trunk_in_bfloat16
from tests.models.conftest import TINY, make_frame


def window(n_frames=3, **kw):
    return [make_frame(seed=i, **kw) for i in range(n_frames)]


@pytest.mark.parametrize("lam", [1.0, 3.5, 10.0, "map"])
def test_apply_of_prepare_equals_forward(lam):
    den = Denoiser(TINY).eval()
    win = window()
    if lam == "map":
        lam = torch.rand(1, 1, 12, 16) * 9 + 1
    with torch.no_grad():
        cache = den.prepare(win, 1)
        torch.testing.assert_close(den.apply(cache, lam), den(win, 1, lam))
        torch.testing.assert_close(den.apply(cache, lam), den.apply(cache, lam))   # cache not consumed


@pytest.mark.parametrize("shape", [(1, 3, 12, 16), (2, 1, 7, 5), (1, 16, 2, 2)])
def test_down_is_two_by_two_average_pooling(shape):
    x = torch.rand(shape, generator=torch.Generator().manual_seed(1)) * 1e3
    torch.testing.assert_close(down(x), torch.nn.functional.avg_pool2d(x, 2))


def test_lambda_changes_the_output_once_the_module_is_trained():
    den = Denoiser(TINY).eval()
    torch.nn.init.normal_(den.specialise.delta)   # untrained module starts neutral
    with torch.no_grad():
        cache = den.prepare(window(), 1)
        assert not torch.allclose(den.apply(cache, 1.0), den.apply(cache, 10.0))


def hostile_cases():
    fire = make_frame()
    fire.color[0, :, 3, 4] = 1e6
    zero = make_frame()
    for t in (zero.color, zero.variance, zero.albedo, zero.normal, zero.depth, zero.motion):
        t.zero_()
    black_albedo = make_frame()
    black_albedo.albedo.zero_()
    nan = make_frame()
    nan.color[0, 0, 1, 1] = float("nan")
    nan.variance[0, :, 2, 2] = float("inf")
    nan.normal[0, 1, 3, 3] = -float("inf")
    nan.depth[0, 0, 4, 4] = float("nan")
    nan.motion[0, 0, 5, 5] = float("nan")
    off = make_frame()
    off.motion.fill_(1e5)
    return {
        "fireflies": [fire, make_frame(seed=1), fire],
        "all-zero": [zero, zero, zero],
        "zero-albedo": [black_albedo] * 3,
        "nan-inf": [nan, make_frame(seed=2), nan],
        "1x1": [make_frame(1, 1, seed=i) for i in range(3)],
        "3x5": [make_frame(3, 5, seed=i) for i in range(3)],
        "one-frame": [make_frame()],
        "motion-off-screen": [off, off, off],
    }


@pytest.mark.parametrize("case", list(hostile_cases()))
@pytest.mark.parametrize("lam", [1.0, 10.0, "map"])
def test_hard_cases_are_finite_in_forward_and_backward(case, lam):
    den = Denoiser(TINY)
    win = hostile_cases()[case]
    center = len(win) // 2
    if lam == "map":                      # per-pixel λ with NaN and out-of-range values
        lam = torch.rand(1, 1, *win[center].size) * 20
        lam[0, 0, 0, 0] = float("nan")
    out = den(win, center, lam)
    h, w = win[center].size
    assert out.shape == (1, 3, h, w)
    assert out.isfinite().all()
    (out / (out.detach().abs() + 1)).sum().backward()     # SMAPE-like scale for the 1e6 case
    grads = [p.grad for p in den.parameters() if p.grad is not None]
    assert grads and all(g.isfinite().all() for g in grads)


def test_past_only_window_and_per_pixel_lambda_and_batch():
    den = Denoiser(TINY).eval()
    win = window(2, n=2)
    with torch.no_grad():
        out = den(win, -1, torch.rand(2, 1, 12, 16) * 9 + 1)
    assert out.shape == (2, 3, 12, 16) and out.isfinite().all()


def test_bad_lambda_map_shape_is_a_clear_error():
    den = Denoiser(TINY)
    with pytest.raises(ValueError, match="λ map"):
        den(window(1), 0, torch.ones(1, 1, 5, 5))


def test_single_scale_single_frame_output_lies_in_convex_hull_of_neighbourhood():
    cfg = replace(TINY, temporal=False, multiscale=False, kernel_size=3)
    den = Denoiser(cfg).eval()
    f = make_frame()
    f.albedo.fill_(1.0)            # demodulation by a constant: hull in radiance == hull in irradiance
    with torch.no_grad():
        out = den([f], 0, 5.0)
    padded = torch.nn.functional.pad(f.color, (1, 1, 1, 1), mode="replicate")
    win = padded.unfold(2, 3, 1).unfold(3, 3, 1)
    assert (out >= win.amin((-1, -2)) - 1e-4).all() and (out <= win.amax((-1, -2)) + 1e-4).all()


def test_temporal_model_with_identical_static_frames_does_not_shift_the_image():
    """Identical frames, zero motion: every frame's kernel sees the same image, so the
    temporal result must be a plain spatial filtering of it — same hull, translation
    equivariant, a flat image stays flat."""
    den = Denoiser(replace(TINY, multiscale=False)).eval()
    f = make_frame(8, 32, motion=False)
    f.albedo.fill_(1.0)
    with torch.no_grad():
        flat = FrameTensors(torch.full_like(f.color, 0.7), f.variance, f.albedo, f.normal, f.depth, torch.zeros(1, 2, 8, 32))
        torch.testing.assert_close(den([flat] * 3, 1), flat.color)
        still = den([f] * 3, 1)
        single = den([f], 0)
        shifted = f.map(lambda name, t: torch.roll(t, 1, dims=-1))
        moved = den([shifted] * 3, 1)
    # away from the zero-padded conv borders (receptive field < 9 px): same result, moved by 1 px
    # (up to the exposure, models.exposure: its 16×16 bins see the shifted column in another bin)
    torch.testing.assert_close(moved[..., 10:-9], still[..., 9:-10], rtol=1e-3, atol=1e-4)
    # temporal on identical frames filters as much as single-frame: same noise level
    assert (still - f.color).abs().mean() == pytest.approx((single - f.color).abs().mean().item(), rel=0.5)


def test_single_frame_and_single_scale_flags_build_smaller_models():
    full = Denoiser(TINY)
    single = Denoiser(replace(TINY, temporal=False, multiscale=False))
    assert single.temporal is None and single.composite is None
    assert sum(p.numel() for p in single.parameters()) < sum(p.numel() for p in full.parameters())
    with torch.no_grad():
        assert single(window(), 1).shape == (1, 3, 12, 16)     # neighbours ignored


def test_lambda_one_is_the_symmetric_network_whatever_the_lambda_module_learns():
    den = Denoiser(TINY).eval()
    win = window()
    with torch.no_grad():
        before = den(win, 1, 1.0)
        for p in [*den.specialise.mix.parameters(), den.specialise.delta]:
            p.add_(torch.randn_like(p))
        torch.testing.assert_close(den(win, 1, 1.0), before)
        torch.testing.assert_close(den(win, 1, torch.ones(1, 1, 12, 16)), before)
        assert not torch.allclose(den(win, 1, 4.0), before)


def test_filter_levels_then_merge_levels_is_apply():
    den = Denoiser(TINY).eval()
    with torch.no_grad():
        cache = den.prepare(window(), 1)
        levels = den.filter_levels(cache, 2.0)
        assert [t.shape[-1] for t in levels] == [16, 8, 4]
        torch.testing.assert_close(den.merge_levels(cache, levels), den.apply(cache, 2.0))


@pytest.mark.parametrize("lam", [4.0, "map"])
def test_banded_lambda_tail_equals_the_whole_level_at_once(monkeypatch, lam):
    den = Denoiser(replace(TINY, oidn_candidate=True)).eval()
    torch.nn.init.normal_(den.specialise.delta)
    win = window()
    if lam == "map":
        lam = torch.rand(1, 1, 12, 16) * 9 + 1
    with torch.no_grad():
        cache = den.prepare(win, 1, torch.rand(1, 3, 12, 16))
    with torch.enable_grad():
        whole = den.apply(cache, lam).detach()                 # autograd: one band per level
    monkeypatch.setattr("models.denoiser.TILE_PIXELS", 3 * 16)  # 3-row bands, a short last band
    with torch.no_grad():
        torch.testing.assert_close(den.apply(cache, lam), whole, rtol=1e-5, atol=1e-6)


def test_scale_compositor_takes_a_fireflys_excess_from_the_firefly_not_its_neighbours():
    # Fine level kept a firefly the coarse level removed: the band swap subtracts the block's
    # excess from all four pixels of the 2×2 block alike; the floor keeps the neighbours at
    # what both levels agree on, and the firefly still gives up its excess.
    torch.manual_seed(0)
    compositor = ScaleCompositor(4)
    with torch.no_grad():
        compositor.alpha[2].bias.fill_(20.0)       # α ≈ 1: take the coarse band everywhere
    fine = torch.ones(1, 3, 8, 8)
    fine[..., 4, 4] = 1000.0
    coarse = torch.ones(1, 3, 4, 4)
    with torch.no_grad():
        out = compositor(fine, coarse)
    neighbours = torch.ones(8, 8, dtype=torch.bool)
    neighbours[4, 4] = False
    assert out[0, :, neighbours].min() >= 1.0 - 1e-5
    assert out[0, :, 4, 4].max() < 900.0                     # ≈ 1000 − 0.56 × 250 (bilinear U)
    unfloored = torch.addcmul(fine, up(compositor.blend_weight(down(fine), coarse)), up(coarse - down(fine)))
    assert unfloored[0, :, neighbours].min() < 0.0             # what the floor prevents


def test_scale_compositor_keeps_a_bright_emitters_coarse_band_off_its_dark_neighbours():
    # A bright emitter fills rows 0-3 (blocks 0-1 of the coarse level), a dark wall rows 4-7.
    # The coarse level is the fine one pooled, except that it holds 10 % more of the emitter
    # (the levels disagree there); the bilinear U spreads that excess onto row 4 of the wall.
    # The cap keeps each wall pixel at most at its own fine or its own coarse block's value.
    compositor = ScaleCompositor(4)
    with torch.no_grad():
        compositor.alpha[2].bias.fill_(20.0)       # α ≈ 1: take the coarse band everywhere
    fine = torch.full((1, 3, 8, 8), 0.1)
    fine[..., :4, :] = 800.0
    coarse = down(fine)
    coarse[..., :2, :] *= 1.1
    with torch.no_grad():
        out = compositor(fine, coarse)
    assert out[..., 4:, :].max() <= 0.1 + 1e-5
    assert out[..., :4, :].min() > 800.0                        # the emitter still gets its band
    uncapped = torch.addcmul(fine, up(compositor.blend_weight(down(fine), coarse)), up(coarse - down(fine)))
    assert uncapped[..., 4, :].min() > 1.0                      # what the cap prevents



def test_the_candidate_cap_keeps_an_emitters_band_off_a_dark_pixel_inside_the_emitters_own_block():
    # The emitter is one pixel of each 2×2 block on row 2; the fine result lost 20 % of its light,
    # the coarse level (OIDN's, pooled) has all of it. The block-wise cap admits up to the coarse
    # block's value on all four pixels; the candidate, known per pixel, says the dark three stay dark.
    compositor = ScaleCompositor(4)
    with torch.no_grad():
        compositor.alpha[2].bias.fill_(20.0)       # α ≈ 1: take the coarse band everywhere
    candidate = torch.full((1, 3, 8, 8), 0.4)
    candidate[..., 2, ::2] = 800.0
    fine = candidate.clone()
    fine[..., 2, ::2] = 640.0
    coarse = down(candidate)
    with torch.no_grad():
        block_capped = compositor(fine, coarse)
        capped = compositor(fine, coarse, candidate=candidate)
    dark = candidate < 1.0
    assert block_capped[dark].max() > 10.0                          # the leak the block cap lets through
    assert capped[dark].max() <= 0.4 + 1e-5
    # the emitter itself is left exactly as the block cap alone leaves it
    torch.testing.assert_close(capped[~dark], block_capped[~dark])

@torch.no_grad()
def test_bfloat16_trunk_changes_the_denoised_image_by_under_a_percent(monkeypatch):
    if not cpu_has_native_bfloat16():
        pytest.skip("this CPU has no native bfloat16: the trunk stays float32")
    den = Denoiser(replace(TINY, width=16, temporal=False)).eval()
    win = [make_frame(32, 32)]
    assert trunk_in_bfloat16(torch.zeros(1))
    fast = den(win, 0, 2.0)
    monkeypatch.setattr("models.denoiser.trunk_in_bfloat16", lambda x: False)
    exact = den(win, 0, 2.0)
    assert fast.dtype == exact.dtype == torch.float32
    assert 0 < ((fast - exact).abs().mean() / exact.abs().mean()) < 0.01


def test_training_keeps_the_trunk_in_float32():
    with torch.enable_grad():
        assert not trunk_in_bfloat16(torch.zeros(1))


def test_scale_compositor_clamp_is_the_floor_and_both_caps_of_its_docstring():
    """The one clamp equals the rule applied step by step: swap capped at max(fine, N(coarse)) and
    at max(fine, candidate), then floored at min(fine, U(coarse))."""
    compositor = ScaleCompositor(4)
    g = torch.Generator().manual_seed(3)
    fine, coarse = torch.rand(2, 3, 8, 10, generator=g) * 5, torch.rand(2, 3, 4, 5, generator=g) * 5
    candidate = torch.rand(2, 3, 8, 10, generator=g) * 5
    with torch.no_grad():
        out = compositor(fine, coarse, candidate=candidate)
        swapped = torch.addcmul(fine, up(compositor.blend_weight(down(fine), coarse)), up(coarse - down(fine)))
    near = torch.nn.functional.interpolate(coarse, scale_factor=2, mode="nearest")
    stepwise = torch.minimum(swapped, torch.maximum(fine, near))
    stepwise = torch.minimum(stepwise, torch.maximum(fine, candidate))
    stepwise = torch.maximum(stepwise, torch.minimum(fine, up(coarse)))
    assert torch.equal(out, stepwise)


def test_a_single_frames_motion_and_sample_count_do_not_change_its_denoised_image():
    den = Denoiser(replace(TINY, temporal=False)).eval()
    moving = make_frame(h=16, w=16)
    moving.spp = torch.full((1, 1, 16, 16), 32.0)
    still = replace(moving, motion=None, spp=None)
    with torch.no_grad():
        assert torch.equal(den([moving], 0), den([still], 0))


def _sky_beside_plaster(h: int = 8, w: int = 16) -> FrameTensors:
    """Left half: the sky seen directly (a camera ray that misses: albedo 0, radiance 1); right
    half: a diffuse surface of albedo 0.8 lit to radiance 0.8. Noise-free, so only the kernels
    decide what crosses the edge between columns 7 and 8."""
    albedo = torch.full((1, 3, h, w), 0.8)
    albedo[..., : w // 2] = 0.0
    color = torch.where(albedo > 0, 0.8, 1.0)
    return FrameTensors(color=color, variance=torch.full_like(color, 1e-4), albedo=albedo,
                        normal=torch.zeros(1, 3, h, w), depth=torch.ones(1, 1, h, w), motion=None)


@torch.no_grad()
def test_albedo_floor_bounds_what_a_zero_albedo_region_carries_onto_its_diffuse_neighbour():
    # One level, no candidate: each output is a convex combination of its 3×3 neighbours'
    # radiance ÷ (demodulation albedo + ε), times its own. On the plaster column beside the sky
    # the sky taps read 1 / 0.01 = 100 without a floor and 1 / 0.11 ≈ 9.1 with floor 0.1.
    config = replace(TINY, temporal=False, multiscale=False)
    model = Denoiser(config).eval()
    frame = _sky_beside_plaster()
    plain = model([frame], 0)
    model.config = replace(config, albedo_floor=0.1)
    floored = model([frame], 0)
    edge = (0.8 + ALBEDO_EPS) / (0.1 + ALBEDO_EPS)      # the most a plaster pixel can read with the floor
    assert floored[..., 8].max() <= edge + 1e-4
    assert plain[..., 8].max() > 3 * floored[..., 8].max()
    # Beyond the kernels' reach each side comes back as it went in, with and without the floor.
    for image in (plain, floored):
        torch.testing.assert_close(image[..., :6], torch.ones_like(image[..., :6]))
        torch.testing.assert_close(image[..., 10:], torch.full_like(image[..., 10:], 0.8))


def test_albedo_floor_is_a_post_training_setting_off_while_training():
    assert DenoiserConfig().albedo_floor == 0.05   # the shipped network's
    assert replace(DenoiserConfig(), albedo_floor=0.1).without_post_training_settings().albedo_floor == 0.0
