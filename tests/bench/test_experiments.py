"""bench/experiments: the allocator-variant switch must act only inside its context, or one
variant's setting would leak into the next measurement (and into the product's loop)."""
from __future__ import annotations

import numpy as np

import service.loop.allocate as allocate
import service.loop.loop as loop
from bench.experiments.allocation_variants import allocator_variant


def test_allocator_variant_applies_its_settings_inside_and_restores_the_product_after():
    weights = np.random.default_rng(0).uniform(0.1, 1.0, (8, 8))
    overrides = {"clamp_percentile": 50.0, "dilate_radius": 0, "floor_fraction": 0.0}
    product = (allocate.error_weights, loop.allocate_samples)
    default = allocate.allocate_samples(weights, 1000, seed=0)
    with allocator_variant(2.0, overrides):
        np.testing.assert_allclose(allocate.error_weights(weights), weights ** 2)
        varied = loop.allocate_samples(weights, 1000, seed=0)
        np.testing.assert_array_equal(varied, allocate.allocate_samples(weights, 1000, seed=0, **overrides))
        assert not np.array_equal(varied, default)
    assert (allocate.error_weights, loop.allocate_samples) == product
    np.testing.assert_array_equal(loop.allocate_samples(weights, 1000, seed=0), default)
