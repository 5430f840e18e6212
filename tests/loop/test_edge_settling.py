"""The error allocator tops up a pixel whose samples all missed beside one that hit
(service.loop.loop.next_counts, allocate.edge_top_up): 16 misses do not show an edge pixel empty."""
from __future__ import annotations

import numpy as np

from service.loop.allocate import EDGE_SETTLE_SPP
from service.loop.loop import next_counts
from service.render.framebuffer import CONVERGED_MIN_SPP, FrameBuffer


def background_with_a_lit_pixel() -> FrameBuffer:
    """16×16, 16 spp each: every sample missed (radiance 0, no hit) but on a noisy surface in
    the middle 8×8 block."""
    n = CONVERGED_MIN_SPP
    buffer = FrameBuffer.empty(16, 16)
    buffer.spp[:] = n
    buffer.radiance_sum[4:12, 4:12] = 0.5 * n
    buffer.radiance_sq_sum[4:12, 4:12] = 0.3 * n
    buffer.depth_sum[4:12, 4:12] = 2.0 * n
    return buffer


def test_a_missed_pixel_beside_a_hit_gets_samples_up_to_the_settling_count() -> None:
    buffer = background_with_a_lit_pixel()
    predicted = np.zeros((16, 16), np.float32)
    predicted[4:12, 4:12] = 0.1
    budget = 16 * 16 * CONVERGED_MIN_SPP
    counts = next_counts("error", buffer, predicted, budget, seed=0)
    assert int(counts.sum()) == budget
    ring = np.zeros((16, 16), bool)
    ring[3:13, 3:13] = True
    ring[4:12, 4:12] = False
    assert (buffer.spp[ring] + counts[ring] >= EDGE_SETTLE_SPP).all(), counts[3:13, 3:13]
    # far from the hit, the samples all agreed and so did their neighbours': only the floor
    assert counts[:3, :3].max() <= 2
