"""FrameBuffer statistics: which pixels count as converged."""
from __future__ import annotations

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
