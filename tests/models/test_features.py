import pytest
import torch

from models.features import (HDR_MAX, PATH_FEATURES, demodulate, sanitize_frame, inverse_log_transform,
                             log_transform, path_features, remodulate, sanitize)
from tests.models.conftest import make_frame


def test_transforms_round_trip():
    x = torch.rand(1, 3, 4, 4) * 1000
    torch.testing.assert_close(inverse_log_transform(log_transform(x)), x)
    albedo = torch.rand(1, 3, 4, 4)
    albedo[0, 0, 0, 0] = 0
    torch.testing.assert_close(remodulate(demodulate(x, albedo), albedo), x)


def test_sanitize_replaces_and_counts_bad_values():
    t = torch.tensor([1.0, float("nan"), float("inf"), -float("inf"), -0.5, 1e9])
    clean, n_bad = sanitize(t)
    assert n_bad == 3
    assert clean.tolist() == [1.0, 0.0, 0.0, 0.0, 0.0, HDR_MAX]


def test_sanitize_fast_path_matches_the_full_path_on_finite_and_huge_values():
    t = torch.tensor([[2.0, -1.0], [3e38, 3e38]])          # finite, but its sum overflows to inf
    clean, n_bad = sanitize(t)
    assert n_bad == 0 and clean.tolist() == [[2.0, 0.0], [HDR_MAX, HDR_MAX]]
    clean, n_bad = sanitize(t[0])
    assert n_bad == 0 and clean.tolist() == [2.0, 0.0]


def test_network_input_is_finite_with_hostile_buffers():
    f = make_frame()
    f.color[0, 0, 0, 0] = float("nan")
    f.variance[0, 1, 1, 1] = float("inf")
    f.albedo.zero_()
    f.depth.zero_()
    x = PATH_FEATURES.build(sanitize_frame(f)[0])
    assert torch.equal(x, torch.cat(path_features(sanitize_frame(f)[0]), 1))
    assert x.shape == (1, PATH_FEATURES.channels, 12, 16)
    assert x.isfinite().all()


def test_albedo_is_clamped_to_a_reflectance_before_demodulation():
    f = make_frame()
    f.albedo[0, :, 2, 3] = 55.0            # a glossy lobe's peak, as some renderers report it
    clean, n_bad = sanitize_frame(f)
    assert n_bad == 0 and float(clean.albedo.max()) == 1.0
