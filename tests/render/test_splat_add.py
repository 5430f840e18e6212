"""The raw image's splat sums added to a FrameBuffer straight from the device packets
(FilmSplat.add_to) land in the same arrays and columns as FrameBuffer.add_splat of host()'s
(H, W, 11) copy, on the first pass (which creates the arrays) and on every later one."""
from __future__ import annotations

import drjit as dr
import numpy as np

from service.render.filters import PixelFilter
from service.render.framebuffer import SPLAT_ARRAYS, FrameBuffer
from service.render.runtime import mitsuba
from service.render.splat import FIRST_PACKET, SECOND_PACKET, FilmSplat

WIDTH, HEIGHT = 7, 5


def splat_with_distinct_sums(mi, offset: float) -> FilmSplat:
    """A FilmSplat whose packets hold a different value in every pixel and slot."""
    pixel_filter = PixelFilter(mi, mi.load_dict({"type": "gaussian"}), WIDTH, HEIGHT)
    splat = FilmSplat(mi, pixel_filter, np.full((HEIGHT, WIDTH), 3))
    pixels = WIDTH * HEIGHT
    splat.first = dr.arange(mi.Float64, pixels * FIRST_PACKET) + offset
    splat.second = dr.arange(mi.Float64, pixels * SECOND_PACKET) * 0.5 + offset
    return splat


def test_splat_sums_added_from_the_packets_equal_add_splat_of_the_host_copy():
    mi = mitsuba()
    direct, reference = FrameBuffer.empty(HEIGHT, WIDTH), FrameBuffer.empty(HEIGHT, WIDTH)
    for offset in (0.25, 1000.0):   # the first pass creates the arrays; the second adds to them
        splat_with_distinct_sums(mi, offset).add_to(direct)
        reference.add_splat(splat_with_distinct_sums(mi, offset).host())
    for name in SPLAT_ARRAYS:
        np.testing.assert_array_equal(getattr(direct, name), getattr(reference, name), err_msg=name)
