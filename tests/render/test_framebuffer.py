"""FrameBuffer statistics: which pixels count as converged."""
from __future__ import annotations

import dataclasses

import numpy as np

from service.render.framebuffer import CONVERGED_MIN_SPP, FrameBuffer


def buffer_with(samples: list[list[float]]) -> FrameBuffer:
    """A 1×N buffer whose pixel i received samples[i] (grey radiance)."""
    buffer = FrameBuffer.empty(1, len(samples))
    for i, values in enumerate(samples):
        values = np.asarray(values, dtype=np.float64)
        buffer.radiance_sum[0, i] = values.sum()
        buffer.radiance_sq_sum[0, i] = (values**2).sum()
        buffer.spp[0, i] = len(values)
    return buffer


def test_a_pixel_is_converged_only_when_enough_samples_all_agreed():
    n = CONVERGED_MIN_SPP
    buffer = buffer_with([[0.0] * n, [0.37] * n, [0.37] * (n - 1) + [0.38], [0.0] * (n - 1)])
    np.testing.assert_array_equal(buffer.converged()[0], [True, True, False, False])


def test_a_surface_whose_samples_were_all_zero_is_not_converged():
    # Rare indirect light can miss 16 times in a row; only a pixel that saw nothing is exact at 0.
    buffer = buffer_with([[0.0] * CONVERGED_MIN_SPP, [0.0] * CONVERGED_MIN_SPP])
    buffer.depth_sum[0, 1] = 3.0 * CONVERGED_MIN_SPP  # pixel 1's primary rays hit a surface
    np.testing.assert_array_equal(buffer.converged()[0], [True, False])


def test_a_missed_pixel_within_the_filters_reach_of_a_lit_one_is_not_converged():
    """Under a wide filter, 16 misses beside the ground do not make a pixel's value exact."""
    n = CONVERGED_MIN_SPP
    buffer = buffer_with([[0.0] * n] * 5 + [[0.5] * (n - 1) + [0.6]])   # five misses, then a noisy surface
    buffer.depth_sum[0, 5] = 2.0 * n
    reach = {footprint: dataclasses.replace(buffer, footprint=footprint).converged()[0] for footprint in (0, 1, 2)}
    np.testing.assert_array_equal(reach[0], [True] * 5 + [False])
    np.testing.assert_array_equal(reach[1], [True] * 4 + [False, False])
    np.testing.assert_array_equal(reach[2], [True] * 3 + [False] * 3)


def test_two_flat_emitters_side_by_side_are_not_converged_where_the_filter_mixes_them():
    n = CONVERGED_MIN_SPP
    buffer = buffer_with([[2.0] * n] * 3 + [[5.0] * n] * 3)
    np.testing.assert_array_equal(buffer.converged()[0], [True] * 6)
    buffer.footprint = 1
    np.testing.assert_array_equal(buffer.converged()[0], [True, True, False, False, True, True])


def test_the_film_edge_does_not_unsettle_a_uniform_background():
    buffer = FrameBuffer.empty(4, 5)
    buffer.spp[:] = CONVERGED_MIN_SPP                       # every ray missed: radiance and depth 0
    buffer.footprint = 2
    assert buffer.converged().all()


def test_a_copy_keeps_the_filters_reach():
    buffer = FrameBuffer.empty(2, 2)
    buffer.footprint = 2
    assert buffer.copy().footprint == 2
