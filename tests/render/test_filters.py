"""Filter importance sampling (service/render/filters.py): offsets drawn from the film's own
filter, truncated to the film where hdrfilm truncates its splats."""
from __future__ import annotations

import numpy as np

from service.render.filters import PixelFilter, footprint_pixels
from service.render.runtime import mitsuba

LANES = 200_000


def offsets(filter_dict: dict, column: int, width: int = 8) -> tuple[np.ndarray, np.ndarray | None]:
    mi = mitsuba()
    pixel_filter = PixelFilter(mi, mi.load_dict(filter_dict), width, width)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(7, LANES)
    position, weight = pixel_filter.sample(sampler, mi.UInt32(np.full(LANES, column)), mi.UInt32(np.full(LANES, 4)))
    x = np.asarray(position.x) - (column + 0.5)
    return x, None if weight is None else np.asarray(weight)


def test_tent_offsets_follow_the_tent_with_unit_weight():
    x, weight = offsets({"type": "tent", "radius": 1.5}, column=4)
    assert weight is None  # sampled exactly: every weight is 1
    assert np.abs(x).max() <= 1.5
    density, edges = np.histogram(x, bins=30, range=(-1.5, 1.5), density=True)
    centres = 0.5 * (edges[1:] + edges[:-1])
    tent = (1 - np.abs(centres) / 1.5) / 1.5  # normalised on [-1.5, 1.5]
    assert np.abs(density - tent).max() < 0.03


def test_tent_at_the_film_border_stays_on_the_film_like_hdrfilm():
    x, _ = offsets({"type": "tent"}, column=0)
    assert x.min() >= -0.5 - 1e-6  # nothing left of the film's edge
    # truncated density ∝ the tent on [-0.5, 1]: mass left of the centre is 0.375 / 0.875
    assert abs((x < 0).mean() - 0.375 / 0.875) < 0.01


def test_gaussian_weights_stay_near_one():
    x, weight = offsets({"type": "gaussian"}, column=4)
    assert np.abs(x).max() <= 2.0 and weight is not None
    assert abs(weight.mean() - 1) < 0.01 and weight.std() < 0.05


def test_the_footprint_counts_the_pixels_a_sample_can_land_in_beyond_its_own():
    mi = mitsuba()
    radii = {name: mi.load_dict({"type": name}).radius() for name in ("box", "tent", "gaussian")}
    assert [footprint_pixels(radii[n]) for n in ("box", "tent", "gaussian")] == [0, 1, 2]
    assert footprint_pixels(1.5) == 1 and footprint_pixels(1.51) == 2
