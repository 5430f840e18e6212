"""Exposure normalisation (models/exposure.py): the statistic scales with the image, the
forward/inverse pair round-trips, and both networks give the same relative result for a frame
multiplied by any factor in [1e-6, 1e12]."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from models.denoiser import Denoiser
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.exposure import EXPOSURE_KEY, Exposure, exposure_metric, exposure_scale
from models.frames import FrameTensors
from tests.models.conftest import TINY, make_frame

SCALES = (1e-6, 1e-3, 1.0, 1e4, 1e8, 1e12)


def scaled(frame: FrameTensors, k: float) -> FrameTensors:
    """The same frame in other units: radiance × k, its variance × k²."""
    return dataclasses.replace(frame, color=frame.color * k, variance=frame.variance * (k * k))


def hdr_frame(seed: int = 0) -> FrameTensors:
    """A frame with HDR content: a dim background, a bright patch and one firefly."""
    f = make_frame(32, 48, motion=False, seed=seed)
    f.color[..., 8:16, 8:20] *= 40.0
    f.color[..., 20, 30] = 5e3
    return f


@pytest.mark.parametrize("k", SCALES)
def test_the_exposure_statistic_scales_with_the_image(k):
    color = hdr_frame().color
    assert float(exposure_metric(color * k) / exposure_metric(color)) == pytest.approx(k, rel=1e-5)
    exposed = Exposure.of(color * k).forward(color * k)
    assert float(exposure_metric(exposed)) == pytest.approx(EXPOSURE_KEY, rel=1e-5)


def test_a_black_or_broken_image_is_left_at_exposure_one():
    assert float(Exposure.of(torch.zeros(1, 3, 8, 8)).scale) == 1.0
    broken = torch.full((1, 3, 8, 8), float("nan"))
    assert float(Exposure.of(broken).scale) == 1.0
    # NaN, Inf and negative noise do not move the statistic of an otherwise valid image
    color = hdr_frame().color
    noisy = color.clone()
    noisy[..., 0, 0], noisy[..., 1, 1], noisy[..., 2, 2] = float("nan"), float("inf"), -5.0
    clean = color.clone()
    clean[..., 0, 0] = clean[..., 1, 1] = clean[..., 2, 2] = 0.0
    assert float(exposure_metric(noisy)) == pytest.approx(float(exposure_metric(clean)), rel=1e-9)


def test_the_scale_moves_exposure_onto_the_nearest_edge_of_a_range():
    e = torch.tensor([0.001, 0.05, 0.5, 20.0], dtype=torch.float64)
    s = exposure_scale(e, 0.01, 1.0)
    torch.testing.assert_close(s * e, torch.tensor([0.01, 0.05, 0.5, 1.0], dtype=torch.float64))


def test_forward_and_inverse_round_trip_radiance_and_variance():
    f = hdr_frame()
    exposure = Exposure.of(f.color * 1e9)
    back = exposure.inverse_frame(exposure.forward_frame(scaled(f, 1e9)))
    torch.testing.assert_close(back.color, f.color * 1e9, rtol=1e-6, atol=0)
    torch.testing.assert_close(back.variance, f.variance * 1e18, rtol=1e-6, atol=0)


@torch.no_grad()
@pytest.mark.parametrize("config", [TINY, dataclasses.replace(TINY, temporal=False, oidn_candidate=True,
                                                               energy_tolerance=0.03, energy_block=8)],
                         ids=["temporal", "single-frame-candidate"])
def test_the_denoiser_gives_the_same_relative_result_at_any_scale(config):
    """Before, every radiance buffer was clamped at HDR_MAX = 1e6 in the scene's own units: a
    scene in physical units (1e10) kept 0.07 % of its energy."""
    den = Denoiser(config).eval()
    window = [hdr_frame(seed=i) for i in range(3)]
    candidate = window[1].color * 0.9 if config.oidn_candidate else None

    def run(k: float) -> torch.Tensor:
        frames = [scaled(f, k) for f in window]
        filtered, centre = den.filtered_window(frames, 1)
        cand = None if candidate is None else candidate * k
        return den(filtered, centre, 2.0, cand) / k

    base = run(1.0)
    for k in SCALES:
        out = run(k)
        assert torch.isfinite(out).all()
        torch.testing.assert_close(out, base, rtol=1e-3, atol=1e-5)
        assert float(out.mean() / window[1].color.mean()) == pytest.approx(float(base.mean() / window[1].color.mean()),
                                                                            rel=1e-4)


@torch.no_grad()
def test_the_lambda_tail_stays_in_the_scene_units():
    den = Denoiser(TINY).eval()
    frames = [scaled(hdr_frame(seed=i), 1e10) for i in range(3)]
    cache = den.prepare(frames, 1)
    full = den(frames, 1, 4.0)
    torch.testing.assert_close(den.apply(cache, 4.0), full)
    assert float(full.mean() / frames[1].color.mean()) > 0.5   # not clamped at HDR_MAX


@torch.no_grad()
def test_the_error_network_predicts_the_same_error_at_any_scale():
    net = ErrorPredictor(ErrorPredictorConfig(width=8, blocks=2, disagreement_input=False)).eval()
    f = dataclasses.replace(hdr_frame(), spp=torch.full((1, 1, 32, 48), 16.0))
    denoised = f.color * 0.95
    base = net(f, denoised)
    for k in SCALES:
        torch.testing.assert_close(net(scaled(f, k), denoised * k), base, rtol=1e-3, atol=1e-6)
