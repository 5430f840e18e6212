"""The lane → pixel map built on the device (service/render/lane_map.py): chunk for chunk the
same lanes as the host's np.repeat reference (tests/render/lane_reference.py), for uniform and uneven
count maps, zero counts and pixels cut between chunks."""
from __future__ import annotations

import numpy as np
import pytest

from service.render.lane_map import independent_chunks, lane_pixels, lane_rows, lane_within_row
from tests.render.lane_reference import expand_counts
from service.render.runtime import mitsuba

COUNT_MAPS = {
    "uniform": np.full((5, 7), 6),
    "uneven with zeros": np.random.default_rng(0).integers(0, 9, size=(6, 5)),
    "one busy pixel": np.array([[0, 40, 0], [1, 0, 2]]),
}


@pytest.mark.parametrize("name", sorted(COUNT_MAPS))
@pytest.mark.parametrize("max_wavefront", [1, 5, 16, 1 << 20])
def test_device_lanes_equal_the_host_expansion_chunk_for_chunk(name, max_wavefront):
    mi = mitsuba()
    counts = COUNT_MAPS[name]
    expected = expand_counts(counts)
    chunks = list(independent_chunks(counts, max_wavefront))
    assert sum(c.size for c in chunks) == len(expected)
    assert all(c.size <= max_wavefront for c in chunks)
    start = 0
    for chunk in chunks:
        traced = np.asarray(lane_pixels(mi, chunk))
        np.testing.assert_array_equal(traced, expected[start:start + chunk.size])
        start += chunk.size


def test_a_lanes_index_within_its_run_counts_from_zero_per_row():
    mi = mitsuba()
    counts = np.array([[3, 0, 1, 4]])
    (chunk,) = independent_chunks(counts, 1 << 20)
    row = lane_rows(mi, chunk)
    within = lane_within_row(mi, chunk, row)
    assert np.asarray(row).tolist() == [0, 0, 0, 1, 2, 2, 2, 2]
    assert np.asarray(within).tolist() == [0, 1, 2, 0, 0, 1, 2, 3]


def test_a_uniform_chunk_continues_the_pixel_the_previous_chunk_cut():
    mi = mitsuba()
    _, second, _ = independent_chunks(np.full((1, 3), 3), 4)
    assert (second.first_pixel, second.skipped, second.size) == (1, 1, 4)
    row = lane_rows(mi, second)
    assert np.asarray(row).tolist() == [0, 0, 1, 1]
    assert np.asarray(lane_within_row(mi, second, row)).tolist() == [1, 2, 0, 1]


def test_an_all_zero_map_has_no_chunks():
    assert list(independent_chunks(np.zeros((3, 3), dtype=int), 8)) == []
