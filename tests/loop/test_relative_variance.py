"""One relative variance, Var / (mean² + ε), with one argument order (mean, variance): the
encoder's feature (models.features) and the variance allocator's (service.loop.allocate, at the
networks' exposure) are the same function."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from models.exposure import Exposure
from models.features import REL_VAR_EPS, relative_variance
from service.loop.allocate import exposed_relative_variance


def test_relative_variance_takes_the_mean_first_and_the_variance_second():
    mean, variance = torch.full((1, 3, 2, 2), 2.0), torch.full((1, 3, 2, 2), 0.4)
    torch.testing.assert_close(relative_variance(mean, variance), torch.full((1, 3, 2, 2), 0.4 / (4.0 + REL_VAR_EPS)))


def test_the_allocators_relative_variance_is_the_features_one_at_the_buffers_exposure():
    rng = np.random.default_rng(0)
    mean = rng.random((32, 32, 3)) * 3.0
    variance = rng.random((32, 32, 3)) * 0.05
    m = torch.from_numpy(mean).permute(2, 0, 1)[None]
    v = torch.from_numpy(variance).permute(2, 0, 1)[None]
    exposure = Exposure.of(m)
    expected = relative_variance(exposure.forward(m), exposure.forward_variance(v))[0].permute(1, 2, 0).numpy()
    allocator = exposed_relative_variance(mean, variance)
    np.testing.assert_allclose(allocator, expected, rtol=1e-6)
    assert not np.allclose(allocator, exposed_relative_variance(variance, mean), rtol=0.1)  # the order matters
    assert allocator.shape == (32, 32, 3) and allocator.dtype == np.float32
    assert float(exposure.scale.flatten()[0]) != pytest.approx(1.0)   # the exposure did act here
