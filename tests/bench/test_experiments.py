"""bench/experiments: the allocator-variant switch must act only inside its context, or one
variant's setting would leak into the next measurement (and into the product's loop)."""
from __future__ import annotations

import numpy as np

import service.loop.allocate as allocate
import service.loop.loop as loop
from bench.experiments.allocation_variants import VARIANTS, allocator_variant


def test_allocator_variant_applies_its_settings_inside_and_restores_the_product_after():
    weights = np.ones((4, 4))
    weights[0, 0] = 100.0
    before = (allocate.error_weights, loop.allocate_samples)
    with allocator_variant(2.0, {"clamp_percentile": None, "dilate_radius": 0, "floor_fraction": 0.0}):
        np.testing.assert_allclose(allocate.error_weights(weights), weights ** 2)
        counts = loop.allocate_samples(allocate.error_weights(weights), 1000)
        assert counts[0, 0] > counts[3, 3]  # no clamp: the outlier keeps its lead (up to the cap)
    assert (allocate.error_weights, loop.allocate_samples) == before


def test_the_shipped_variant_changes_nothing():
    assert VARIANTS["shipped"] == (1.0, {})
