"""Temporal accumulation: a single-frame denoiser pools a window's consistent samples (models/accumulation.py)."""
from __future__ import annotations

import dataclasses

import torch
import torch.nn.functional as F

from models.accumulation import accumulate_window, consistent_pixels, neighbourhood_range
from models.denoiser import Denoiser
from models.frames import FrameTensors

from .conftest import TINY, make_frame

H, W = 10, 14


def still_frame(seed: int, spp: float | None = 16.0, level: float = 1.0) -> FrameTensors:
    """One seed's render of a still view: the same surfaces (albedo and depth ramps across x), the
    radiance `level` ± its noise."""
    g = torch.Generator().manual_seed(seed)
    ramp = torch.linspace(0.0, 1.0, W).view(1, 1, 1, W).expand(1, 1, H, W)
    noise = (torch.rand(1, 3, H, W, generator=g) - 0.5) * 0.2
    normal = torch.zeros(1, 3, H, W)
    normal[:, 2] = 1.0
    return FrameTensors(color=level + noise, variance=torch.full((1, 3, H, W), 0.01),
                        albedo=(0.2 + 0.4 * ramp).expand(1, 3, H, W).clone(), normal=normal, depth=2.0 + ramp,
                        spp=None if spp is None else torch.full((1, 1, H, W), spp))


def test_neighbourhood_range_is_the_min_and_max_of_each_3x3_window():
    x = torch.rand(2, 4, 9, 7, generator=torch.Generator().manual_seed(3))
    padded = F.pad(x, (1, 1, 1, 1), mode="replicate")
    lo, hi = neighbourhood_range(x)
    torch.testing.assert_close(hi, F.max_pool2d(padded, 3, stride=1), rtol=0, atol=0)
    torch.testing.assert_close(lo, -F.max_pool2d(-padded, 3, stride=1), rtol=0, atol=0)


def test_a_still_window_with_zero_motion_pools_like_one_without_motion():
    window = [still_frame(s) for s in (21, 22, 23)]
    zero = [dataclasses.replace(f, motion=torch.zeros(1, 2, H, W)) for f in window]
    torch.testing.assert_close(accumulate_window(zero, 1).color, accumulate_window(window, 1).color)


def test_a_one_frame_window_comes_back_unchanged():
    frame = still_frame(0)
    assert accumulate_window([frame], 0) is frame


def test_a_still_window_pools_every_sample_with_its_count():
    window = [still_frame(1, 16.0), still_frame(2, 32.0), still_frame(3, 16.0)]
    pooled = accumulate_window(window, 1)
    expected = (16 * window[0].color + 32 * window[1].color + 16 * window[2].color) / 64
    torch.testing.assert_close(pooled.color, expected)
    # Var of a weighted mean: Σ n² Var / (Σ n)² = (256 + 1024 + 256) · 0.01 / 64²
    torch.testing.assert_close(pooled.variance, torch.full_like(pooled.variance, 1536 * 0.01 / 4096))
    torch.testing.assert_close(pooled.spp, torch.full_like(pooled.spp, 64.0))
    assert pooled.albedo is window[1].albedo and pooled.normal is window[1].normal


def test_frames_without_counts_pool_as_equals_and_keep_no_count_map():
    window = [still_frame(s, spp=None) for s in (4, 5, 6)]
    pooled = accumulate_window(window, 0)
    torch.testing.assert_close(pooled.color, sum(f.color for f in window) / 3)
    assert pooled.spp is None


def test_a_disoccluded_neighbour_pixel_is_left_out():
    center, other = still_frame(7), still_frame(8)
    albedo = other.albedo.clone()
    albedo[..., 2:6, 3:8] = 0.95                                   # another surface moved in here
    other = dataclasses.replace(other, albedo=albedo)
    pooled = accumulate_window([center, other], 0)
    moved = torch.zeros(1, 1, H, W, dtype=torch.bool)
    moved[..., 2:6, 3:8] = True
    torch.testing.assert_close(pooled.color[moved.expand_as(pooled.color)], center.color[moved.expand_as(center.color)])
    torch.testing.assert_close(pooled.spp[~moved], torch.full_like(pooled.spp[~moved], 32.0))


def test_a_guide_that_moves_with_the_seed_on_an_edge_is_still_pooled():
    """A pixel straddling an edge averages both sides, in a proportion each seed draws anew: the
    neighbour's mixed albedo lies within the center's 3×3 range there, but not on a flat patch."""
    center, other = still_frame(19), still_frame(20)
    edge = center.albedo.clone()
    edge[..., 7:] = 0.9                                             # a sharp edge between columns 6 and 7
    center = dataclasses.replace(center, albedo=edge)
    mixed = edge.clone()
    mixed[..., 7] = 0.6                                             # the other seed saw some of the left side
    mixed[..., 11] = 0.6                                            # and a patch that is not there
    ok = consistent_pixels(center, dataclasses.replace(other, albedo=mixed))[0, 0]
    assert bool(ok[:, 7].all()) and not bool(ok[:, 11].any())


def test_a_light_change_beyond_the_noise_is_left_out_but_noise_is_pooled():
    center, brighter = still_frame(9), still_frame(10, level=3.0)   # 2.0 apart, noise σ ≈ 0.14 per frame
    assert not consistent_pixels(center, brighter).any()
    assert consistent_pixels(center, still_frame(11)).all()
    torch.testing.assert_close(accumulate_window([brighter, center], 1).color, center.color)


def test_a_moving_neighbour_is_pooled_where_its_motion_points():
    past = still_frame(12)
    shift = 2
    # frame t shows frame t-1 moved right by `shift`: pixel x of t was at x - shift in t-1
    current = past.map(lambda _, t: torch.roll(t, shifts=shift, dims=-1))
    motion = torch.zeros(1, 2, H, W)
    motion[:, 0] = -shift
    current = dataclasses.replace(current, color=current.color + 0.01, motion=motion)
    pooled = accumulate_window([past, current], 1)
    inside = torch.zeros(1, 1, H, W, dtype=torch.bool)
    inside[..., shift:] = True                                      # columns whose source is on screen
    torch.testing.assert_close(pooled.spp[inside], torch.full_like(pooled.spp[inside], 32.0))
    torch.testing.assert_close(pooled.spp[~inside], torch.full_like(pooled.spp[~inside], 16.0))
    torch.testing.assert_close(pooled.color[..., shift:], current.color[..., shift:] - 0.005)


def test_pooled_radiance_stays_within_the_frames_samples():
    window = [still_frame(s) for s in (13, 14, 15)]
    pooled = accumulate_window(window, 1).color
    stack = torch.stack([f.color for f in window])
    assert bool((pooled >= stack.amin(0) - 1e-6).all()) and bool((pooled <= stack.amax(0) + 1e-6).all())


@torch.no_grad()
def test_a_single_frame_denoiser_filters_its_windows_pooled_center():
    model = Denoiser(dataclasses.replace(TINY, temporal=False)).eval()
    window = [still_frame(s) for s in (16, 17, 18)]
    filtered, center = model.filtered_window(window, 1)
    assert center == 0 and len(filtered) == 1
    torch.testing.assert_close(filtered[0].color, accumulate_window(window, 1).color)
    torch.testing.assert_close(model(window, 1), model(filtered, 0))
    kept, center = Denoiser(TINY).eval().filtered_window(window, 1)
    assert center == 1 and kept is window   # a temporal network weighs its neighbours itself


@torch.no_grad()
def test_a_neighbour_of_nan_inf_and_fireflies_leaves_the_pooled_center_finite():
    """Sanitised first (NaN → 0, ±Inf → the range's ends): a neighbour's NaN pixel then disagrees
    with the center's light and is left out; the whole denoise stays finite and ≥ 0."""
    bad = still_frame(24)
    color, variance = bad.color.clone(), bad.variance.clone()
    color[0, :, 1, 1] = float("nan")
    color[0, :, 2, 2] = float("inf")
    color[0, 0, 3, 3] = 1e6
    variance[0, :, 4, 4] = float("nan")
    window = [dataclasses.replace(bad, color=color, variance=variance), still_frame(25), still_frame(26)]
    model = Denoiser(dataclasses.replace(TINY, temporal=False)).eval()
    (pooled,), _ = model.filtered_window(window, 1)
    assert torch.isfinite(pooled.color).all() and torch.isfinite(pooled.variance).all()
    assert float(pooled.spp[0, 0, 1, 1]) == 32.0                   # the NaN pixel was left out
    out = model(window, 1)
    assert torch.isfinite(out).all() and float(out.min()) >= 0
