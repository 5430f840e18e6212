"""Sample allocators: exact budgets, floor, cap, proportionality, determinism and odd inputs.

Property-style checks run as plain loops over seeded random cases (hypothesis is not installed).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from service.loop.allocate import (
    ALLOCATORS,
    DEFAULT_CAP_MULTIPLE,
    EDGE_SETTLE_SPP,
    allocate_samples,
    allocation_weights,
    edge_top_up,
    error_weights,
    iteration_budget,
    uniform_weights,
    variance_weights,
)


def _random_cases(n: int, seed: int = 1234):
    """(weights, budget) pairs over awkward shapes and budgets, including budget < pixels."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        h, w = int(rng.integers(1, 40)), int(rng.integers(1, 40))
        pixels = h * w
        budget = int(rng.choice([0, 1, rng.integers(0, pixels + 1), rng.integers(pixels, 50 * pixels + 1)]))
        weights = rng.lognormal(0.0, 2.0, (h, w)) * (rng.random((h, w)) < rng.random())
        yield weights, budget


def test_budget_is_exact_over_random_shapes_and_budgets():
    for i, (weights, budget) in enumerate(_random_cases(300)):
        counts = allocate_samples(weights, budget, seed=i)
        assert counts.shape == weights.shape
        assert counts.dtype == np.int64
        assert counts.min() >= 0
        assert int(counts.sum()) == budget


def test_budget_is_exact_with_any_option_mix():
    rng = np.random.default_rng(7)
    for i, (weights, budget) in enumerate(_random_cases(200, seed=99)):
        counts = allocate_samples(
            weights,
            budget,
            floor_fraction=float(rng.choice([0.0, 0.05, 0.5, 1.0])),
            clamp_percentile=[None, 50.0, 95.0, 100.0][i % 4],
            dilate_radius=int(rng.integers(0, 4)),
            max_per_pixel=[None, 1, 2, 7][(i // 4) % 4],
            seed=i,
        )
        assert int(counts.sum()) == budget


def test_budget_zero_gives_all_zeros():
    counts = allocate_samples(np.random.default_rng(0).random((5, 7)), 0)
    assert counts.shape == (5, 7) and not counts.any()


def test_one_by_one_image_takes_the_whole_budget():
    for budget in (0, 1, 16, 12345):
        assert allocate_samples(np.array([[0.3]]), budget).tolist() == [[budget]]
    assert allocate_samples(np.array([[np.nan]]), 9).tolist() == [[9]]


def test_budget_below_pixel_count_gives_at_most_one_each_when_uniform():
    counts = allocate_samples(np.ones((20, 30)), 137, seed=3)
    assert int(counts.sum()) == 137
    assert set(np.unique(counts)) <= {0, 1}


def test_budget_below_pixel_count_favours_heavy_pixels():
    weights = np.zeros((30, 30))
    weights[10:13, 10:13] = 1.0
    counts = allocate_samples(weights, 20, dilate_radius=0, floor_fraction=0.0)
    assert int(counts.sum()) == 20
    assert int(counts[10:13, 10:13].sum()) >= 9  # the heavy block is served before the rest


def test_floor_gives_every_pixel_its_floor_share():
    rng = np.random.default_rng(5)
    for _ in range(100):
        h, w = int(rng.integers(1, 50)), int(rng.integers(1, 50))
        pixels = h * w
        budget = int(rng.integers(pixels, 40 * pixels + 1))
        fraction = float(rng.choice([0.05, 0.2, 0.5]))
        weights = np.zeros((h, w))
        weights[rng.integers(h), rng.integers(w)] = 1e6  # everything else would starve
        counts = allocate_samples(weights, budget, floor_fraction=fraction, dilate_radius=0)
        assert counts.min() >= math.floor(fraction * budget / pixels)


def test_cap_is_respected_and_the_excess_redistributed():
    rng = np.random.default_rng(11)
    for i in range(100):
        h, w = int(rng.integers(2, 40)), int(rng.integers(2, 40))
        pixels = h * w
        budget = int(rng.integers(pixels, 20 * pixels))
        cap = int(rng.integers(math.ceil(budget / pixels), 40))
        weights = rng.pareto(0.7, (h, w))  # heavy tail: the cap binds
        counts = allocate_samples(weights, budget, max_per_pixel=cap, clamp_percentile=None, seed=i)
        assert counts.max() <= cap
        assert int(counts.sum()) == budget


def test_cap_fraction_and_default_cap_are_respected():
    weights = np.zeros((32, 32))
    weights[0, 0] = 1.0
    budget = 32 * 32 * 4
    counts = allocate_samples(weights, budget, dilate_radius=0, floor_fraction=0.0)
    assert counts[0, 0] == math.floor(DEFAULT_CAP_MULTIPLE * budget / weights.size)
    counts = allocate_samples(weights, budget, dilate_radius=0, cap_fraction_per_pixel=0.001)
    assert counts.max() <= math.floor(0.001 * budget)
    assert int(counts.sum()) == budget


def test_infeasible_cap_is_raised_and_no_sample_is_lost():
    weights = np.random.default_rng(2).random((10, 10))
    counts = allocate_samples(weights, 350, max_per_pixel=1)
    assert int(counts.sum()) == 350
    assert counts.max() <= 4  # raised to ⌈350 / 100⌉, no further


def test_zero_weight_pixels_take_what_the_capped_ones_cannot():
    weights = np.zeros((10, 10))
    weights[:2] = 1.0  # 20 weighted pixels, capped at 3 each → 60 of 300
    counts = allocate_samples(weights, 300, floor_fraction=0.0, dilate_radius=0, max_per_pixel=3)
    assert int(counts.sum()) == 300
    assert (counts[:2] == 3).all() and (counts[2:] == 3).all()  # the rest evenly, within the cap


def test_clamp_limits_an_outlier_to_the_percentile():
    weights = np.random.default_rng(6).uniform(1.0, 2.0, (20, 20))
    weights[3, 3] = 1e9  # a firefly in the error map
    counts = allocate_samples(weights, 400 * 16, dilate_radius=0)
    others = np.delete(counts.ravel(), 3 * 20 + 3)
    assert counts[3, 3] <= others.max() + 1  # no more than the clamp-percentile pixels get


def test_clamp_uses_positive_weights_so_sparse_maps_survive():
    # 0.5% of pixels carry weight: a percentile over all pixels would be 0 and erase them.
    weights = np.zeros((40, 40))
    weights[np.arange(8) * 5, np.arange(8) * 5] = np.arange(1.0, 9.0)
    counts = allocate_samples(weights, 1600 * 4, dilate_radius=0)
    hot = counts[np.arange(8) * 5, np.arange(8) * 5]
    assert hot.min() > 4 * np.median(counts)


def test_error_proportional_on_two_regions_matches_the_analytic_expectation():
    h, w, budget, floor = 40, 40, 40 * 40 * 32, 0.05
    weights = np.ones((h, w))
    weights[:, w // 2 :] = 4.0
    counts = allocate_samples(weights, budget, floor_fraction=floor, dilate_radius=1)
    # Dilation by 1 lifts the last column of the light half to 4; nothing is clamped or capped.
    dilated = weights.copy()
    dilated[:, w // 2 - 1] = 4.0
    expected = budget * ((1 - floor) * dilated / dilated.sum() + floor / dilated.size)
    assert np.abs(counts - expected).max() < 1.0  # largest remainder moves each by < 1
    light, heavy = expected[0, 0], expected[0, -1]
    assert counts[:, : w // 2 - 1].mean() == pytest.approx(light, abs=0.5)
    assert counts[:, w // 2 :].mean() == pytest.approx(heavy, abs=0.5)


def test_error_proportional_without_floor_or_dilation_is_one_to_four():
    weights = np.ones((40, 40))
    weights[:, 20:] = 4.0
    counts = allocate_samples(weights, 40 * 40 * 30, floor_fraction=0.0, dilate_radius=0)
    assert counts[:, 20:].mean() / counts[:, :20].mean() == pytest.approx(4.0, rel=0.01)


def test_same_seed_gives_the_same_allocation():
    for i, (weights, budget) in enumerate(_random_cases(50, seed=3)):
        a = allocate_samples(weights, budget, seed=i)
        b = allocate_samples(weights.copy(), budget, seed=i)
        assert np.array_equal(a, b)


def test_seeds_differ_only_in_tie_breaks():
    # Distinct continuous weights (no clamp, no dilation, which would create ties): no ties,
    # so the seed cannot matter.
    weights = np.random.default_rng(8).random((25, 25)) + 0.01
    a = allocate_samples(weights, 5000, clamp_percentile=None, dilate_radius=0, seed=0)
    b = allocate_samples(weights, 5000, clamp_percentile=None, dilate_radius=0, seed=1)
    assert np.array_equal(a, b)
    # A uniform map with fewer samples than pixels is all ties: seeds pick different pixels,
    # but every pixel still gets 0 or 1 and the total is the same.
    a = allocate_samples(np.ones((25, 25)), 300, seed=0)
    b = allocate_samples(np.ones((25, 25)), 300, seed=1)
    assert not np.array_equal(a, b)
    assert np.abs(a - b).max() <= 1 and a.sum() == b.sum() == 300


def test_nan_inf_and_negative_weights_are_safe():
    weights = np.ones((8, 8))
    weights[0, 0], weights[1, 1], weights[2, 2], weights[3, 3] = np.nan, np.inf, -np.inf, -5.0
    counts = allocate_samples(weights, 640, dilate_radius=0)
    assert int(counts.sum()) == 640
    assert counts[0, 0] < counts[5, 5] and counts[1, 1] < counts[5, 5]  # garbage counts as 0
    assert counts.min() >= math.floor(0.05 * 640 / 64)


def test_all_zero_or_all_nan_weights_fall_back_to_uniform():
    for weights in (np.zeros((6, 9)), np.full((6, 9), np.nan), np.full((6, 9), -1.0)):
        counts = allocate_samples(weights, 6 * 9 * 7)
        assert (counts == 7).all()


def test_all_mass_in_one_pixel_is_dilated_to_its_neighbours():
    weights = np.zeros((16, 16))
    weights[8, 8] = 1.0
    budget = 16 * 16 * 8 + 3  # not a multiple of the pixel count
    counts = allocate_samples(weights, budget, seed=4)
    assert int(counts.sum()) == budget
    block = counts[7:10, 7:10]
    outside = counts.copy()
    outside[7:10, 7:10] = -1
    assert block.max() - block.min() <= 1  # the 3×3 neighbourhood is treated as one
    assert block.min() > outside.max()


def test_floor_only_pixels_next_to_a_hard_pixel_get_only_the_floor_despite_dilation():
    weights = np.zeros((16, 16))
    weights[8, 8] = 1.0
    settled = np.zeros((16, 16), bool)
    settled[8, 9] = settled[7, 7] = True  # neighbours the dilation would reach
    budget = 16 * 16 * 8
    counts = allocate_samples(weights, budget, floor_fraction=0.05, floor_only=settled, seed=1)
    assert int(counts.sum()) == budget
    far = counts[:4, :4]  # zero weight, nowhere near the hard pixel: the floor (plus the cap's spill)
    assert counts[settled].max() <= far.max()
    assert counts[8, 7] > 4 * far.max()  # an unsettled neighbour still gets the dilated weight


def test_edge_pixels_whose_samples_agreed_are_topped_up_to_the_settling_count():
    converged = np.ones((4, 6), bool)
    settled = converged.copy()
    settled[1, 2] = settled[2, 3] = False   # agreed, beside pixels that did not
    converged[0, 0] = settled[0, 0] = False  # sampled by its error, not topped up
    spp = np.full((4, 6), 16)
    spp[2, 3] = EDGE_SETTLE_SPP + 10         # already past the count
    top_up = edge_top_up(converged, settled, spp, budget=24 * 16)
    expected = np.zeros((4, 6), np.int64)
    expected[1, 2] = EDGE_SETTLE_SPP - 16
    np.testing.assert_array_equal(top_up, expected)


def test_edge_top_up_takes_at_most_half_the_budget():
    converged, settled = np.ones((8, 8), bool), np.zeros((8, 8), bool)   # every pixel an edge
    top_up = edge_top_up(converged, settled, np.full((8, 8), 16), budget=64 * 16)
    assert 0 < top_up.sum() <= 64 * 16 // 2
    assert top_up.max() - top_up.min() <= 1


def test_all_mass_in_a_corner_pixel_dilates_inside_the_image():
    weights = np.zeros((5, 5))
    weights[0, 0] = 1.0
    counts = allocate_samples(weights, 250, dilate_radius=2, floor_fraction=0.0)
    assert int(counts.sum()) == 250
    assert (counts[:3, :3] > 0).all()


def test_huge_image_allocates_exactly():
    weights = np.random.default_rng(0).lognormal(0.0, 2.0, (1024, 2048))
    counts = allocate_samples(weights, 16 * weights.size + 12345, dilate_radius=2)
    assert int(counts.sum()) == 16 * weights.size + 12345


def test_bad_arguments_are_rejected_with_a_message():
    with pytest.raises(ValueError, match="budget"):
        allocate_samples(np.ones((2, 2)), -1)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        allocate_samples(np.ones((2, 2, 3)), 4)
    with pytest.raises(ValueError, match="floor_fraction"):
        allocate_samples(np.ones((2, 2)), 4, floor_fraction=1.5)
    with pytest.raises(ValueError, match="empty"):
        allocate_samples(np.ones((0, 3)), 4)
    assert allocate_samples(np.ones((0, 3)), 0).shape == (0, 3)


def test_iteration_budget_doubles_the_total():
    pixels = 64 * 48
    total = 16 * pixels  # the first, uniform iteration
    means = [total / pixels]
    for _ in range(3):
        added = iteration_budget(total)
        assert added == total  # as many as all earlier iterations together
        total += added
        means.append(total / pixels)
    assert means == [16, 32, 64, 128]
    with pytest.raises(ValueError):
        iteration_budget(0)


def test_weight_builders():
    assert (uniform_weights((3, 4)) == 1).all()
    rv = np.stack([np.full((2, 2), 1.0), np.full((2, 2), 2.0), np.full((2, 2), np.nan)], axis=2)
    assert variance_weights(rv) == pytest.approx(np.ones((2, 2)))  # NaN channel counts as 0
    assert variance_weights(np.full((2, 2), 0.5)) == pytest.approx(np.full((2, 2), 0.5))
    assert (error_weights(np.array([[0.1, np.inf], [-1.0, 0.2]])) == [[0.1, 0], [0, 0.2]]).all()


def test_allocation_weights_knows_every_allocator_and_rejects_others():
    assert ALLOCATORS == ("error", "variance", "uniform")
    inputs = {"predicted_error": np.ones((3, 4)), "relative_variance": np.ones((3, 4, 3))}
    for kind in ALLOCATORS:
        assert allocation_weights(kind, shape=(3, 4), **inputs).shape == (3, 4)
    with pytest.raises(ValueError, match="error, variance, uniform"):
        allocation_weights("random", shape=(3, 4), **inputs)
    with pytest.raises(ValueError, match="predicted_error"):
        allocation_weights("error", shape=(3, 4))
    with pytest.raises(ValueError, match="shape"):
        allocation_weights("error", predicted_error=np.ones((2, 2)), shape=(3, 4))
